"""Shared fixtures (shared constants and helpers are in helpers.py). One Prefect test server per pytest
session (it takes ~15 s to start), only for the tests that ask for it: all of them are marked ``system``,
and ``pytest -m "not system"`` (the fast loop) starts no server at all."""

from __future__ import annotations

import os
import tempfile

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
# torch's OpenMP threads spin after each parallel region; beside the compiled rasterizer's threads on 2 cores that
# makes both many times slower (flows.cli.main sets the same for users)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# verified model checksums go to a per-session file, not the user's cache (models/runtime/onnxio.checksum_cache_path)
os.environ.setdefault("NAVCRAFTER_CHECKSUM_CACHE",
                      os.path.join(tempfile.mkdtemp(prefix="navcrafter-tests-"), "checksums.json"))

import functools  # noqa: E402
import io  # noqa: E402
import shlex  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from helpers import BUCKET, TINY, TINY_MODELS_SIZE, cached_export  # noqa: E402

from navcrafter.schemas.config import RunConfig  # noqa: E402

# Fixtures that start a server: a test whose fixtures include one of them must be marked ``system``
# (see pytest_collection_modifyitems), so that ``pytest -m "not system"`` never starts one.
SERVER_FIXTURES = {
    "prefect_api_url": "the session's Prefect test server",
    "s3_endpoint": "moto's S3 server",
    "server": "a `prefect server start` process (test_worker)",
    "restartable_server": "a `prefect server start` process (test_faults)",
}


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Every test that starts a server carries ``@pytest.mark.system`` (or its module's ``pytestmark``);
    one that requests a server fixture without it is a usage error, not a silent member of the fast loop.
    (Tests that start subprocesses or workers, or kill them, without these fixtures are marked by hand.)"""
    unmarked = []
    for item in items:
        servers = [SERVER_FIXTURES[name] for name in item.fixturenames if name in SERVER_FIXTURES]
        if servers and item.get_closest_marker("system") is None:
            unmarked.append(f"{item.nodeid} (starts {'; '.join(servers)})")
    if unmarked:
        raise pytest.UsageError("tests that start a server must be marked @pytest.mark.system:\n  "
                                + "\n  ".join(unmarked))
    schedule_for_xdist(items)


def module_fixture_modules(items) -> set[str]:
    """The test modules that define a module-scoped fixture of their own (a server, a built image, a scene run
    once): their tests must stay on one pytest-xdist worker, or the fixture is set up again on the other."""
    modules = set()
    for item in items:
        module = _module(item)
        for defs in item._fixtureinfo.name2fixturedefs.values():
            if any(d.scope == "module" and d.baseid == module for d in defs):
                modules.add(module)
    return modules


def _module(item) -> str:
    return item.nodeid.split("::")[0]


def _long(item) -> bool:
    return bool(item.get_closest_marker("slow") or item.get_closest_marker("system"))


def schedule_for_xdist(items) -> None:
    """Orders the run for ``--dist loadgroup --no-loadscope-reorder`` (deploy/local/run-tests.sh): each module
    with module fixtures becomes one work unit (an ``xdist_group`` named after it), and the long units are handed
    out first (those modules when they hold a slow or system test, then every other slow or system test, then the
    other modules with module fixtures), the short ones last, so that neither core idles at the end while the
    other finishes a long module alone. Stable: the order inside each rank is the collection's, the same in every
    worker (xdist requires it)."""
    grouped = module_fixture_modules(items)
    long_modules = {_module(it) for it in items if _long(it)}

    def rank(item) -> int:
        if _module(item) in grouped:
            return 0 if _module(item) in long_modules else 2
        return 1 if _long(item) else 3

    for item in items:
        if _module(item) in grouped:
            item.add_marker(pytest.mark.xdist_group(_module(item)))
    items.sort(key=rank)


# Processes of our own that a test may start only when marked ``subprocess`` (or ``system``): Python (the CLI, a
# script, torchrun's workers), torchrun, navcrafter, prefect, a browser. Tools that libraries run inside a call
# (ffmpeg behind imageio, ...) are not refused.
OWN_PROCESSES = ("python", "torchrun", "navcrafter", "prefect", "chromium", "chrome", "google-chrome")


def _own_process(args) -> str | None:
    argv = shlex.split(args) if isinstance(args, str) else [str(a) for a in args]
    if not argv:
        return None
    name = Path(argv[0]).name
    if argv[0] == sys.executable or any(name.startswith(p) for p in OWN_PROCESSES):
        return " ".join(argv[:4])
    return None


@pytest.fixture(autouse=True)
def _subprocesses_are_marked(request, monkeypatch):
    """A test that starts a process of its own must say so (``@pytest.mark.subprocess`` or ``system``): the fast
    loop (``-m "not system and not slow"``) leaves subprocess tests to the marked runs they belong to. Anything
    else fails at the ``Popen`` with the fix."""
    if request.node.get_closest_marker("subprocess") or request.node.get_closest_marker("system"):
        yield
        return
    real = subprocess.Popen

    class Refused(real):
        def __init__(self, args, *a, **kw):
            what = _own_process(args)
            if what is not None:
                pytest.fail(f"{request.node.nodeid} starts a process ({what}) without @pytest.mark.subprocess "
                            "(or system): mark it", pytrace=False)
            super().__init__(args, *a, **kw)

    monkeypatch.setattr(subprocess, "Popen", Refused)
    yield


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


@pytest.fixture(scope="module")
def s3_endpoint():
    """A moto S3 server on a free port, a bucket (``helpers.BUCKET``) on it, and the AWS env pointing at it,
    for one test module."""
    pytest.importorskip("s3fs")
    pytest.importorskip("moto.server")
    import logging

    import boto3
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)  # one log line per request otherwise
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    url = f"http://{host}:{port}"
    with pytest.MonkeyPatch.context() as mp:
        for var in ("AWS_PROFILE", "AWS_SESSION_TOKEN", "AWS_ENDPOINT_URL_S3", "FSSPEC_S3_ENDPOINT_URL"):
            mp.delenv(var, raising=False)
        mp.setenv("AWS_ACCESS_KEY_ID", "testing")
        mp.setenv("AWS_SECRET_ACCESS_KEY", "testing")
        mp.setenv("AWS_DEFAULT_REGION", "us-east-1")
        mp.setenv("AWS_ENDPOINT_URL", url)
        boto3.client("s3", endpoint_url=url, region_name="us-east-1").create_bucket(Bucket=BUCKET)
        try:
            yield url
        finally:
            server.stop()


@pytest.fixture(scope="session")
def demo_photos(tmp_path_factory) -> Path:
    """The three demo scenes (small photos to keep the suite fast)."""
    from navcrafter.models.simulation.demo import write_demo_collection

    folder = tmp_path_factory.mktemp("demo") / "photos"
    write_demo_collection(folder, width=320, height=240, supersample=1)
    return folder


@pytest.fixture(scope="session")
def export_cache(request, tmp_path_factory):
    """``export_cache(dest, name, args, export)``: the files of ``export(folder)`` in ``dest`` (see
    ``helpers.cached_export``). The tiny ONNX exports take about 2 minutes of a session on 2 cores, so they
    are kept in pytest's cache folder (.pytest_cache) under a hash of the package's models/ code, the calling
    test file, ``args`` and the torch/ONNX versions, and made again only when one of those changes.
    ``pytest --cache-clear`` or ``-p no:cacheprovider`` exports afresh: then into the run's own temporary
    folder, made once per run however many pytest-xdist workers ask (each worker has its own session
    fixtures; the run's base temp folder, the parent of a worker's, is shared by them)."""
    cache = getattr(request.config, "cache", None)
    if cache is not None:
        folder = cache.mkdir("navcrafter-onnx-exports")
    else:
        base = tmp_path_factory.getbasetemp()
        run = base.parent if hasattr(request.config, "workerinput") else base  # xdist worker: the run's folder
        folder = run / "navcrafter-onnx-exports"
    return functools.partial(cached_export, folder)


@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory, export_cache) -> Path:
    """All three learned roles exported with random weights (seed 0, tiny configs):
    MODEL_DIR/{synthesizer,geometry,monodepth}. Tests must not modify it (copy it first)."""
    from navcrafter.models.zoo.exporters import export_all

    root = tmp_path_factory.mktemp("models")
    T, H, W = TINY_MODELS_SIZE
    args = dict(num_frames=T, height=H, width=W, random="tiny", seed=0, prompt="a room")
    export_cache(root, "tiny-models", args, lambda out: bool(export_all(out, **args)))
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
