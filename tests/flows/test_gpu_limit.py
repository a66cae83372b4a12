"""Model-running steps occupy a slot of a named Prefect global concurrency limit (``gpu_limit``), and
cost no API call when none is configured."""

from __future__ import annotations

import uuid

import pytest
from conftest import TINY

from navcrafter.flows import explore


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


def test_gpu_step_holds_a_slot_while_it_runs(gpu_limit):
    seen = []

    def step(store_uri: str, scene_id: str, config, run_id: str, k: int | None = None) -> str:
        seen.append(_active_slots(gpu_limit))
        return scene_id

    wrapped = explore._gpu_bound(step)
    config = TINY.model_copy(update={"gpu_limit": gpu_limit})
    assert wrapped(store_uri="s", scene_id="a", config=config, run_id="r", k=1) == "a"
    assert wrapped("s", "b", config, "r") == "b"  # positional arguments too
    assert seen == [1, 1]
    assert _active_slots(gpu_limit) == 0  # released afterwards


def test_no_limit_means_no_concurrency_call(monkeypatch):
    def forbidden(*a, **k):
        raise AssertionError("no API call without gpu_limit")

    monkeypatch.setattr(explore, "concurrency", forbidden)
    wrapped = explore._gpu_bound(lambda store_uri, scene_id, config, run_id: scene_id)
    assert wrapped(store_uri="s", scene_id="a", config=TINY, run_id="r") == "a"
    explore.check_gpu_limit(TINY)  # nothing to check


def test_unknown_limit_is_a_clear_error(prefect_api_url):
    config = TINY.model_copy(update={"gpu_limit": "no-such-limit"})
    with pytest.raises(ValueError, match=r"prefect gcl create no-such-limit --limit"):
        explore.check_gpu_limit(config)


def test_limit_is_not_part_of_any_step_key():
    config = TINY.model_copy(update={"gpu_limit": "navcrafter-gpu"})
    for step in ("ingest", "geometry", "plan", "synthesize", "lift", "export", "evaluate"):
        assert config.step_config(step) == TINY.step_config(step)
