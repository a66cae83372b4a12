"""The `onnx` backend end to end: exported (tiny, random-weight) Wan2.1 camera control, VGGT and MoGe-2 models run
by onnxruntime inside the Prefect flow, on a photo without any ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import TINY, TINY_MODELS_SIZE

from navcrafter.schemas.layout import GEOMETRY, LIFT, SYNTHESIZE
from navcrafter.schemas.store import Store
from navcrafter.tasks.backends import RANDOM_WEIGHTS_LABEL, onnx_problems, run_label


def _onnx_config(models: Path, **updates):
    T, H, W = TINY_MODELS_SIZE  # the session's tiny export (conftest.tiny_models)
    synthesis = TINY.synthesis.model_copy(update={"steps": 2, "num_frames": T, "height": H, "width": W})
    return TINY.model_copy(update={"backend": "onnx", "model_dir": models, "iterations": 1, "synthesis": synthesis,
                                   **updates})


def test_preflight_names_what_is_missing(tiny_models, tmp_path):
    assert onnx_problems(_onnx_config(tiny_models)) == []
    problems = onnx_problems(_onnx_config(tmp_path / "nowhere"))
    assert len(problems) == 1 and "does not exist" in problems[0] and "export-all" in problems[0]
    wrong = _onnx_config(tiny_models, synthesis=TINY.synthesis.model_copy(update={"num_frames": 13}))
    assert any("exported for 5 frames" in p and "synthesis.num_frames" in p for p in onnx_problems(wrong))
    fun = _onnx_config(tiny_models, synthesis=TINY.synthesis.model_copy(update={
        "num_frames": TINY_MODELS_SIZE[0], "height": TINY_MODELS_SIZE[1], "width": TINY_MODELS_SIZE[2],
        "model": "fun-camera"}))
    assert any("is 'navcrafter', the run asks for synthesis.model='fun-camera'" in p for p in onnx_problems(fun))
    (tmp_path / "geometry").mkdir()
    problems = onnx_problems(_onnx_config(tmp_path))
    assert any("export-synthesizer" in p for p in problems) and any("export-geometry" in p for p in problems)
    assert run_label(_onnx_config(tiny_models)) == RANDOM_WEIGHTS_LABEL


def test_a_base_exported_without_trained_camera_control_is_labelled_everywhere_random_weights_would_be(tmp_path):
    """A real Wan base without camera-control weights ignores the cameras: runs with it say so (the label of the
    summary, manifest, PLY comment and trajectory.json; the band burnt into videos and figures)."""
    import json

    from navcrafter.tasks.backends import CAMERA_CONTROL_UNTRAINED_LABEL, run_band

    def manifest(role: str, weights: dict) -> None:
        (tmp_path / role).mkdir(exist_ok=True)
        (tmp_path / role / "manifest.json").write_text(json.dumps(
            {"format": "navcrafter-onnx", "format_version": 1, "kind": role, "architecture": "x", "config": {},
             "weights": weights, "files": {}}))

    manifest("geometry", {"source": "checkpoint"})
    manifest("synthesizer", {"source": "checkpoint", "path": "/wan", "files": {}})
    config = _onnx_config(tmp_path)
    assert run_label(config) == CAMERA_CONTROL_UNTRAINED_LABEL and run_band(config) == "CAMERA CONTROL UNTRAINED"
    manifest("synthesizer", {"source": "checkpoint", "path": "/wan", "files": {},
                             "control": {"path": "/control", "files": {"camera_control.safetensors": "ab"}}})
    assert run_label(config) is None and run_band(config) is None  # trained control: no label
    manifest("monodepth", {"source": "random", "seed": 0})
    assert run_band(config) == "RANDOM WEIGHTS"  # random weights say more


@pytest.mark.system
def test_onnx_backend_explores_a_photo_end_to_end(prefect_api_url, collection, tiny_models, tmp_path):
    from navcrafter.flows.explore import explore_collection

    photos = tmp_path / "photos"
    photos.mkdir()
    # a "real photo": no ground truth exists for it, so only learned models can explore it
    (photos / "photo.png").write_bytes((collection / "no-groundtruth.png").read_bytes())
    store = tmp_path / "store"
    run = explore_collection(str(photos), str(store), _onnx_config(tiny_models))
    (result,) = run.scenes
    assert result.status == "done", result.error
    scene = Store(str(store)).scene(result.scene_id)
    frames = scene.read(SYNTHESIZE, 1, "frames")
    assert frames.shape == (*TINY_MODELS_SIZE, 3) and frames.dtype == np.uint8 and frames.std() > 0
    assert scene.status(SYNTHESIZE, 1).attrs["synthesizer_model"] == "navcrafter"
    # release_models (default): each step's models were released when it ended (the process's cached backend)
    from navcrafter.tasks.backends import create_backend

    backend = create_backend(_onnx_config(tiny_models))
    assert not any(getattr(backend, r).loaded for r in ("synthesizer", "geometry", "mono_depth"))
    geo, lift = scene.status(GEOMETRY).attrs, scene.status(LIFT, 1).attrs
    assert geo["n_points"] > 0 and lift["n_points"] >= 1 and np.isfinite(lift["scale"])
    summary = (store / run.summary).read_text()
    assert RANDOM_WEIGHTS_LABEL in summary and "backend 'onnx'" in summary
    exports = store / result.outputs
    assert json.loads((exports / "trajectory.json").read_text())["label"] == RANDOM_WEIGHTS_LABEL
    assert RANDOM_WEIGHTS_LABEL.encode() in (exports / "cloud.ply").read_bytes()[:2000]


def test_a_lazy_role_is_released_and_loads_again():
    from navcrafter.models.roles import Backend
    from navcrafter.tasks.backends import _LazyRole

    made = []

    class Role:
        def predict(self, x):
            return x + 1

    def factory():
        made.append(1)
        return Role()

    role = _LazyRole("onnx", factory)
    backend = Backend(name="onnx", synthesizer=object(), geometry=role, mono_depth=object())
    assert not role.loaded and backend.release() == []
    assert role.predict(1) == 2 and role.loaded and len(made) == 1
    assert role.predict(2) == 3 and len(made) == 1  # kept while loaded
    assert backend.release() == ["geometry"] and not role.loaded
    assert role.predict(3) == 4 and len(made) == 2  # created again on the next use
