"""``navcrafter view`` (flows/tools/viewer.py, flows/cli/view.py): the scene's nodes on a real viser server, the CLI's
usage errors, and the page drawn by a real headless browser (tests/browser.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from browser import find_chromium, screenshot
from helpers import free_port

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def viewer_store(tmp_path_factory):
    """A store of two tiny demo scenes: tabletop-0 with the 3DGS fit, room-0 without (simulation mode)."""
    from navcrafter.models.simulation.demo import write_demo_collection
    from navcrafter.schemas.config import RunConfig
    from navcrafter.tasks.ingest import ingest
    from navcrafter.tasks.runner import run_scene

    root = tmp_path_factory.mktemp("viewer")
    write_demo_collection(root / "photos", width=320, height=240, supersample=1)
    store = str(root / "store")
    ids = {}
    for name, fit in (("tabletop-0.png", True), ("room-0.png", False)):
        cfg = RunConfig.load(preset="tiny", overrides={"fit.enabled": fit})
        res = ingest(store, str(root / "photos" / name), cfg, "t")
        run_scene(store, res.scene_id, cfg, "t")
        ids[name] = res.scene_id
    return store, ids


@pytest.fixture
def viser_server():
    import viser

    s = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    yield s
    s.stop()


@pytest.mark.slow
def test_scene_nodes_gaussians_clouds_frustums_candidates(viewer_store, viser_server):
    import viser

    from navcrafter.flows.tools.viewer import ROOT, build_scene, read_scene
    from navcrafter.models.simulation import LABEL
    from navcrafter.schemas.store import Store

    store, ids = viewer_store
    sid = ids["tabletop-0.png"]
    data = read_scene(Store(store, create=False), sid)
    assert data.label == LABEL and data.gaussians is not None and len(data.iterations) == 2
    it1 = data.iterations[0]
    assert len(it1.candidates) > 1
    rej = next(c for c in range(len(it1.candidates)) if c != it1.chosen)  # the explorer's chosen one comes first
    it1.collides[rej] = True  # as if G had rejected a candidate of iteration 1 that was not chosen
    view = build_scene(viser_server, store, sid, data)
    n = view.nodes
    assert isinstance(n[f"{ROOT}/gaussians"], viser.GaussianSplatHandle)
    assert isinstance(n[f"{ROOT}/input"], viser.CameraFrustumHandle)
    for k in (1, 2):
        T = len(data.iterations[k - 1].trajectory)
        planned = [x for x in n if x.startswith(f"{ROOT}/iter_{k}/planned/f")]
        estimated = [x for x in n if x.startswith(f"{ROOT}/iter_{k}/estimated/v")]
        assert len(planned) == T and len(estimated) == len(data.iterations[k - 1].estimated) > 0
        assert n[planned[0]].color != n[estimated[0]].color  # planned and estimated differ in colour
        cands = [x.rsplit("/", 1)[1] for x in n if x.startswith(f"{ROOT}/iter_{k}/candidates/")]
        assert len(cands) == len(data.iterations[k - 1].candidates)
        assert sum(c.startswith("chosen") for c in cands) == 1
    assert f"{ROOT}/iter_1/candidates/rejected_{rej:03d}" in n
    it2 = data.iterations[1]  # iteration 2 shows exactly the candidates its plan stored as rejected by G
    assert {x.rsplit("/", 1)[1] for x in n if x.startswith(f"{ROOT}/iter_2/candidates/rejected_")} == \
        {f"rejected_{c:03d}" for c in range(len(it2.candidates)) if it2.collides[c] and c != it2.chosen}
    # the latest cloud shows; an earlier iteration adds and shows its own, hiding later cameras
    assert n[f"{ROOT}/cloud/iter_2"].visible
    view.show_iteration(0)
    assert n[f"{ROOT}/cloud/iter_0"].visible and not n[f"{ROOT}/cloud/iter_2"].visible
    assert not n[f"{ROOT}/iter_1"].visible
    view.show_iteration(1, cumulative=False)
    assert n[f"{ROOT}/iter_1"].visible and not n[f"{ROOT}/iter_2"].visible
    view.set_layer("gaussians", False)
    assert not n[f"{ROOT}/gaussians"].visible
    frame = view.show_frame(10)  # clip 2, frame 1
    assert frame.shape == (64, 64, 3) and isinstance(n[f"{ROOT}/video/current"], viser.CameraFrustumHandle)
    np.testing.assert_allclose(n[f"{ROOT}/video/current"].position, data.iterations[1].trajectory[1][:3, 3],
                               atol=1e-6)
    view.show_frame(None)
    assert f"{ROOT}/video/current" not in n


def test_pose_and_gaussian_conversions():
    import torch

    from navcrafter.flows.tools.viewer import frustum_fov, gaussian_splat_arrays, pose_to_viser
    from navcrafter.models.camera.cameras import look_at, quat_wxyz_to_matrix
    from navcrafter.models.gaussians.model import GaussianModel

    c2w = look_at(np.array([1.0, -0.5, 0.2]), np.array([0.0, 0.0, 3.0]))
    wxyz, pos = pose_to_viser(c2w)
    np.testing.assert_allclose(quat_wxyz_to_matrix(wxyz), c2w[:3, :3], atol=1e-9)
    np.testing.assert_allclose(pos, c2w[:3, 3])
    assert frustum_fov(np.array([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]]), 64) == pytest.approx(
        2 * np.arctan(32 / 50))
    g = GaussianModel(torch.zeros(2, 3), torch.tensor([[2.0, 0, 0, 0], [1, 0, 0, 1]]),
                      torch.log(torch.tensor([[1.0, 2, 3], [1, 2, 3]])), torch.tensor([0.0, 10.0]),
                      torch.zeros(2, 3), torch.zeros(2, 0, 3))
    a = gaussian_splat_arrays(g)
    np.testing.assert_allclose(a["covariances"][0], np.diag([1.0, 4, 9]), atol=1e-5)
    np.testing.assert_allclose(a["covariances"][1], np.diag([4.0, 1, 9]), atol=1e-5)  # 90 deg about z
    np.testing.assert_allclose(a["rgbs"], 0.5) and np.testing.assert_allclose(a["opacities"][:, 0], [0.5, 1.0],
                                                                               atol=1e-4)


@pytest.mark.slow
def test_viewer_gui_switches_scenes_and_says_when_there_is_no_fit(viewer_store, viser_server):
    from navcrafter.flows.tools.viewer import NO_FIT, ROOT, build_viewer
    from navcrafter.schemas.store import Store
    from navcrafter.tasks.readers import SceneNotFound, resolve_scene

    store, ids = viewer_store
    st = Store(store, create=False)
    assert resolve_scene(st, "room-0.png") == resolve_scene(st, ids["room-0.png"][:8]) == ids["room-0.png"]
    with pytest.raises(SceneNotFound, match="navcrafter status"):
        resolve_scene(st, "nothing-like-it")
    viewer = build_viewer(viser_server, store, "tabletop-0")
    assert viewer.view.data.scene_id == ids["tabletop-0.png"] and "no_fit" not in viewer.gui
    room = next(lab for lab, sid in viewer.choices.items() if sid == ids["room-0.png"])
    viewer.gui["scene"].value = room  # as a user picking it in the dropdown
    assert viewer.view.data.scene_id == ids["room-0.png"] and viewer.view.data.gaussians is None
    assert NO_FIT in viewer.gui["no_fit"].content and f"{ROOT}/gaussians" not in viewer.view.nodes
    assert f"{ROOT}/cloud/iter_2" in viewer.view.nodes  # the cloud still shows
    viewer.gui["iteration"].value = 1
    assert viewer.view.iteration == 1 and "iteration 1" in viewer.gui["iteration_info"].content


@pytest.mark.slow
def test_cli_usage_errors(viewer_store, tmp_path):
    from typer.testing import CliRunner

    from navcrafter.flows.cli import app

    store, _ = viewer_store
    runner = CliRunner()
    res = runner.invoke(app, ["view", str(tmp_path / "none")])
    assert res.exit_code == 2 and "no navcrafter store" in res.output and "navcrafter status" in res.output
    res = runner.invoke(app, ["view", store, "no-such-scene"])
    assert res.exit_code == 2 and "'no-such-scene'" in res.output and f"navcrafter status {store}" in res.output


def _pixels(path):
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float32)


@pytest.mark.system  # starts the viewer as a subprocess and a browser
def test_browser_draws_the_scene(viewer_store, tmp_path):
    if find_chromium() is None:
        pytest.skip("chromium is not installed (bash deploy/local/setup.sh test installs it)")
    import viser

    store, ids = viewer_store
    empty = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        screenshot(f"http://127.0.0.1:{empty.get_port()}/", tmp_path / "empty.png", 960, 640, wait_ms=6000)
    finally:
        empty.stop()
    port = free_port()
    env = {**os.environ, "COLUMNS": "200"}
    proc = subprocess.Popen([sys.executable, "-m", "navcrafter.flows.cli", "view", store, "tabletop-0",
                             "--port", str(port)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=env)
    try:
        lines = []
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "Ctrl-C to stop" in line:
                break
        out = "".join(lines)
        assert f"http://127.0.0.1:{port}" in out, out
        assert "SIMULATION MODE" in out
        shot = screenshot(f"http://127.0.0.1:{port}/", tmp_path / "scene.png", 960, 640, wait_ms=8000)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    scene, blank = _pixels(shot), _pixels(tmp_path / "empty.png")
    assert scene.shape == blank.shape == (640, 960, 3)
    assert scene.std() > 20  # not a blank page
    # the scene is drawn: the 3D canvas (left of the GUI panel) differs from an empty viser's
    left = slice(200, 640), slice(0, 600)
    diff = np.abs(scene[left] - blank[left]).max(axis=-1)
    assert (diff > 40).mean() > 0.01, f"only {(diff > 40).mean():.4f} of the canvas differs from an empty viewer"


@pytest.mark.system  # starts the viewer as a subprocess
def test_ctrl_c_stops_the_viewer_even_with_a_callback_that_never_returns(viewer_store):
    """viser's callback pool has non-daemon worker threads that the interpreter joins at exit: one stuck callback
    used to keep `navcrafter view` alive after Ctrl-C for ever. The viewer must end within seconds regardless."""
    store, _ = viewer_store
    code = (
        "import sys, threading, viser\n"
        "class Stuck(viser.ViserServer):\n"
        "    def __init__(self, *a, **k):\n"
        "        super().__init__(*a, **k)\n"
        "        self._thread_executor.submit(threading.Event().wait)  # a callback that never returns\n"
        "viser.ViserServer = Stuck\n"
        "from navcrafter.flows.cli import main\n"
        f"sys.argv = ['navcrafter', 'view', {store!r}, 'tabletop-0', '--port', '{free_port()}']\n"
        "main()\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "COLUMNS": "200"})
    try:
        deadline = time.monotonic() + 60
        out = ""
        while time.monotonic() < deadline and "Ctrl-C to stop" not in out:
            line = proc.stdout.readline()
            if not line:
                break
            out += line
        assert "Ctrl-C to stop" in out, out
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
        assert "navcrafter view: stopped" in proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
