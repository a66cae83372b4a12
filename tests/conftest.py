"""Shared fixtures. One Prefect test server per pytest session (it takes ~15 s to start)."""

from __future__ import annotations

import os
import tempfile

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
# verified model checksums go to a per-session file, not the user's cache (models/onnxio.checksum_cache_path)
os.environ.setdefault("NAVCRAFTER_CHECKSUM_CACHE",
                      os.path.join(tempfile.mkdtemp(prefix="navcrafter-tests-"), "checksums.json"))

import io  # noqa: E402
import shutil  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from navcrafter.schemas.config import RunConfig  # noqa: E402

TINY = RunConfig.load(preset="tiny")
DEMO = ("room-0.png", "street-0.png", "tabletop-0.png")
# file -> (what the error says, the fix it suggests)
BAD = {"notes.txt": ("not an image", "remove it"), "empty.png": ("empty", "remove it"),
       "truncated.png": ("corrupt or truncated", "re-export"),
       "no-groundtruth.png": ("no simulation ground truth", "navcrafter demo-data")}


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny tensors gain nothing from torch's threads (and lose a lot when the cores are busy): a test module
    takes it with ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def prefect_api_url() -> str:
    """A real Prefect API (temporary SQLite server) for the whole session; its URL is also handed to
    subprocesses so they do not start servers of their own."""
    from prefect.settings import PREFECT_API_URL
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        yield PREFECT_API_URL.value()


@pytest.fixture(scope="session")
def demo_photos(tmp_path_factory) -> Path:
    """The three demo scenes (small photos to keep the suite fast)."""
    from navcrafter.models.simulation.demo import write_demo_collection

    folder = tmp_path_factory.mktemp("demo") / "photos"
    write_demo_collection(folder, width=320, height=240, supersample=1)
    return folder


# frames, height, width of the session's tiny exported synthesizer
TINY_MODELS_SIZE = (5, 32, 32)


@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory) -> Path:
    """All three learned roles exported once per session with random weights (seed 0, tiny configs):
    MODEL_DIR/{synthesizer,geometry,monodepth}. Tests must not modify it (copy it first)."""
    from navcrafter.models.runtime.exporters import export_all

    root = tmp_path_factory.mktemp("models")
    T, H, W = TINY_MODELS_SIZE
    export_all(root, num_frames=T, height=H, width=W, random="tiny", seed=0, prompt="a room")
    return root


@pytest.fixture
def tiny() -> RunConfig:
    return RunConfig.load(preset="tiny")


@pytest.fixture(scope="session")
def collection(demo_photos, tmp_path_factory) -> Path:
    """The demo photos plus one file of each kind of trouble."""
    folder = tmp_path_factory.mktemp("collection")
    shutil.copytree(demo_photos, folder, dirs_exist_ok=True)
    # the same bytes as room-0.png under a name that sorts first and has no ground truth beside it
    (folder / "a-copy-of-room.png").write_bytes((demo_photos / "room-0.png").read_bytes())
    (folder / "notes.txt").write_text("shopping list")
    (folder / "empty.png").write_bytes(b"")
    (folder / "truncated.png").write_bytes((demo_photos / "room-0.png").read_bytes()[:3000])
    from PIL import Image

    rng = np.random.default_rng(0)
    buf = io.BytesIO()
    Image.fromarray(rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)).save(buf, format="PNG")
    (folder / "no-groundtruth.png").write_bytes(buf.getvalue())  # a "real photo": valid, no ground truth
    return folder


@pytest.fixture(scope="session")
def full_run(prefect_api_url, collection, tmp_path_factory):
    from navcrafter.flows.explore import explore_collection

    store = tmp_path_factory.mktemp("full") / "store"
    run = explore_collection(str(collection), str(store), TINY)
    return store, run
