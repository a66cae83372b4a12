"""The synthesize step: each clip is conditioned on the view at its first camera (the working image, then the
previous clip's last frame), with the input photo and its camera as an extra reference from the second clip."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from helpers import TINY


def _explore(store: str, photo, steps: list[tuple[str, int | None]]) -> str:
    """Ingest ``photo`` and run ``steps`` ((name, k), in order) of its scene with the tiny config."""
    from navcrafter.tasks.ingest import ingest
    from navcrafter.tasks.runner import run

    sid = ingest(store, str(photo), TINY, "t").scene_id
    for name, k in steps:
        run(store, sid, name, TINY, "t", k)
    return sid


@pytest.fixture
def requests(monkeypatch) -> list:
    """The requests the simulation's synthesizer gets (copies), in order."""
    import navcrafter.models.simulation.backend as sim_backend

    seen = []

    class Recording(sim_backend.SimulationSynthesizer):
        def simulate(self, request, start=None):
            seen.append(copy.deepcopy(request))
            return super().simulate(request, start)

    monkeypatch.setattr(sim_backend, "SimulationSynthesizer", Recording)
    return seen


FIRST = [("geometry", None), ("plan", 1), ("synthesize", 1), ("lift", 1)]


def test_clip_2_is_conditioned_on_clip_1s_last_frame_with_the_photo_as_reference(demo_photos, tmp_path, requests):
    from navcrafter.schemas.layout import GEOMETRY, INGEST, LIFT, PLAN, SYNTHESIZE
    from navcrafter.schemas.store import Store

    store = str(tmp_path / "store")
    sid = _explore(store, demo_photos / "room-0.png", [*FIRST, ("plan", 2), ("synthesize", 2)])
    scene = Store(store).scene(sid)
    work, clip1 = scene.read(INGEST, None, "work_image"), scene.read(SYNTHESIZE, 1, "frames")
    assert len(requests) == 2
    first, second = requests
    np.testing.assert_array_equal(first.image, work)  # clip 1: the input view
    assert first.reference_image is None and first.reference_c2w is None
    np.testing.assert_array_equal(second.image, clip1[-1])  # clip 2: the view at its first camera
    # clip 2 starts where clip 1's last frame is estimated to be (the lift always lifts it)
    lift1 = scene.read_all(LIFT, 1)
    np.testing.assert_array_equal(second.trajectory[0], lift1["c2w"][list(lift1["view_index"]).index(len(clip1) - 1)])
    assert not np.allclose(second.trajectory[0], scene.read(PLAN, 1, "trajectory")[-1])  # not where it was asked
    np.testing.assert_array_equal(second.reference_image, work)
    np.testing.assert_array_equal(second.reference_c2w, scene.read(GEOMETRY, None, "c2w"))
    np.testing.assert_array_equal(second.reference_c2w, np.eye(4))
    # the synthesizer reproduces its conditioning image as frame 0, and its hidden truth continues from there
    np.testing.assert_array_equal(scene.read(SYNTHESIZE, 2, "frames")[0], clip1[-1])
    np.testing.assert_array_equal(scene.read(SYNTHESIZE, 2, "true_c2w")[0], scene.read(SYNTHESIZE, 1, "true_c2w")[-1])


def test_a_plan_that_does_not_start_where_the_last_clip_ended_fails_the_synthesize_step(demo_photos, tmp_path):
    from navcrafter.schemas.layout import PLAN
    from navcrafter.tasks.common import StepError
    from navcrafter.tasks.plan import plan
    from navcrafter.tasks.runner import run
    from navcrafter.tasks.steps import execute

    def elsewhere(ctx):  # the real plan, moved 0.1 world units sideways
        write = ctx.write

        def shifted(name, array):
            if name == "trajectory":
                array = np.array(array, copy=True)
                array[:, 0, 3] += 0.1
            write(name, array)

        ctx.write = shifted
        return plan(ctx)

    store = str(tmp_path / "store")
    sid = _explore(store, demo_photos / "room-0.png", FIRST)
    execute(store, sid, PLAN, 2, TINY, "t", elsewhere)
    with pytest.raises(StepError, match=r"iter_2/synthesize failed: ValueError: the trajectory of iteration 2 "
                                        r"does not start at the estimated last pose of iteration 1 .*not available"):
        run(store, sid, "synthesize", TINY, "t", 2)
