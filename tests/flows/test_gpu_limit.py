"""Model-running steps occupy a slot of a named Prefect global concurrency limit (``gpu_limit``), and
cost no API call when none is configured."""

from __future__ import annotations

import re
import uuid

import pytest
from helpers import TINY

from navcrafter.flows import explore
from navcrafter.schemas.layout import STEPS


def _active_slots(name: str) -> int:
    from prefect.client.orchestration import get_client

    with get_client(sync_client=True) as client:
        return client.read_global_concurrency_limit_by_name(name).active_slots


@pytest.fixture
def gpu_limit(prefect_api_url) -> str:
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.actions import GlobalConcurrencyLimitCreate

    name = f"navcrafter-gpu-{uuid.uuid4().hex[:8]}"
    with get_client(sync_client=True) as client:
        client.create_global_concurrency_limit(GlobalConcurrencyLimitCreate(name=name, limit=1))
    yield name
    with get_client(sync_client=True) as client:
        client.delete_global_concurrency_limit_by_name(name)


@pytest.mark.system
def test_gpu_step_holds_a_slot_while_it_runs(gpu_limit):
    config = TINY.model_copy(update={"gpu_limit": gpu_limit})
    gpu_steps = [s for s in STEPS.values() if s.gpu]
    assert {s.name for s in gpu_steps} == {"geometry", "synthesize", "lift", "fit", "refine"}  # the model steps
    seen = [explore.in_gpu_slot(s, config, lambda: _active_slots(gpu_limit)) for s in gpu_steps]
    assert seen == [1] * len(gpu_steps)
    assert explore.in_gpu_slot(STEPS["plan"], config, lambda: _active_slots(gpu_limit)) == 0  # CPU work: no slot
    assert _active_slots(gpu_limit) == 0  # released afterwards


def test_no_limit_means_no_concurrency_call(monkeypatch):
    def forbidden(*a, **k):
        raise AssertionError("no API call without gpu_limit")

    monkeypatch.setattr(explore, "concurrency", forbidden)
    assert explore.in_gpu_slot(STEPS["lift"], TINY, lambda: "a") == "a"
    assert explore.gpu_limit_problem(TINY) is None  # nothing to check
    assert explore.preflight(TINY) == []


@pytest.mark.system
def test_unknown_limit_is_a_clear_error(prefect_api_url):
    config = TINY.model_copy(update={"gpu_limit": "no-such-limit"})
    assert re.search(r"prefect gcl create no-such-limit --limit", explore.gpu_limit_problem(config))
    # checked before any work starts: explore_collection raises it (ValueError) before ingesting anything
    assert any("no-such-limit" in p for p in explore.preflight(config))


def test_limit_is_not_part_of_any_step_key():
    config = TINY.model_copy(update={"gpu_limit": "navcrafter-gpu"})
    for step in ("ingest", "geometry", "plan", "synthesize", "lift", "export", "evaluate"):
        assert config.step_config(step) == TINY.step_config(step)
