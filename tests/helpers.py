"""Constants and helpers that several test modules share (a plain module: no tests, no fixtures).

Test modules import from here (``from helpers import TINY``), never from each other or from conftest;
fixtures live in conftest.py. ``tests`` is on pytest's ``pythonpath`` (pyproject.toml).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
import uuid
from collections import Counter
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from navcrafter.schemas.config import RunConfig

if TYPE_CHECKING:
    from navcrafter.schemas.store import Store

# --------------------------------------------------------------------------------------------------
# The session's inputs (conftest's fixtures build them)
# --------------------------------------------------------------------------------------------------
TINY = RunConfig.load(preset="tiny")
DEMO = ("room-0.png", "street-0.png", "tabletop-0.png")
# file -> (what the error says, the fix it suggests)
BAD = {"notes.txt": ("not an image", "remove it"), "empty.png": ("empty", "remove it"),
       "truncated.png": ("corrupt or truncated", "re-export"),
       "no-groundtruth.png": ("no simulation ground truth", "navcrafter demo-data")}
# frames, height, width of the session's tiny exported synthesizer (conftest.tiny_models)
TINY_MODELS_SIZE = (5, 32, 32)


# --------------------------------------------------------------------------------------------------
# ONNX exports kept between sessions (conftest's ``export_cache`` fixture)
# --------------------------------------------------------------------------------------------------
# what an export's files depend on besides the package's models/ code and the caller's arguments
EXPORT_STACK = ("torch", "onnx", "onnxscript", "onnx-ir", "onnxruntime", "diffusers", "transformers",
                "safetensors", "numpy")
EXPORT_ENV = ("NAVCRAFTER_ONNX_OPTIMIZE",)
_KEEP_PER_NAME = 3  # cached versions kept per export name (older ones are deleted)


def _export_key(name: str, args: dict, caller: Path) -> str:
    """Hash of everything an export's files depend on: every file of the package's models/ tree (the
    exporters, the architectures, their key lists), the calling test file, ``args``, the installed
    torch/ONNX stack and the exporter's environment switches."""
    import navcrafter.models

    h = hashlib.sha256(json.dumps([name, args], sort_keys=True, default=repr).encode())
    for root in sorted(Path(p) for p in navcrafter.models.__path__):
        for path in sorted(root.rglob("*")):
            if path.is_file() and "__pycache__" not in path.parts:
                h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    h.update(caller.read_bytes())
    stack = {}
    for dist in EXPORT_STACK:
        try:
            stack[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            stack[dist] = None
    h.update(json.dumps([sys.version, stack, {v: os.environ.get(v) for v in EXPORT_ENV}]).encode())
    return h.hexdigest()[:24]


def cached_export(cache: Path | None, dest: Path, name: str, args: dict, export: Callable[[Path], Any]) -> Any:
    """``export(folder)`` writes an export (a directory of files) into a new ``folder``; this puts the same
    files in ``dest`` and returns what ``export`` returned (JSON round trip: return plain data).

    With a ``cache`` folder the files come from an export made earlier by the same code (same models/ tree,
    same calling test file, same ``args``, same torch/ONNX stack: see ``_export_key``), and a missing one is
    made once and kept. A lock file beside the entry makes concurrent callers (the pytest-xdist workers of one
    run, or two sessions sharing pytest's cache) wait for the one that exports instead of exporting again.
    ``cache=None`` exports into ``dest`` every time. ``args`` must name every value the export depends on that
    is not in those files (sizes, seeds, configs).
    """
    if cache is None:
        return json.loads(json.dumps(export(Path(dest))))
    from filelock import FileLock

    caller = Path(sys._getframe(1).f_code.co_filename)  # the fixture that asks (conftest's is a partial)
    cache = Path(cache)
    cache.mkdir(parents=True, exist_ok=True)
    entry = cache / f"{name}-{_export_key(name, args, caller)}"
    with FileLock(str(entry) + ".lock"):
        if not (entry / "result.json").is_file():
            tmp = Path(tempfile.mkdtemp(dir=cache, prefix=f".{name}-"))
            try:
                (tmp / "result.json").write_text(json.dumps(export(tmp / "files")))
                os.replace(tmp, entry)  # complete or absent
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
            versions = sorted((p for p in cache.glob(f"{name}-*") if p.is_dir()),
                              key=lambda p: p.stat().st_mtime, reverse=True)
            for old in versions[_KEEP_PER_NAME:]:
                shutil.rmtree(old, ignore_errors=True)
                Path(str(old) + ".lock").unlink(missing_ok=True)
        shutil.copytree(entry / "files", Path(dest), dirs_exist_ok=True)  # a copy: no test can change the cached files
    return json.loads((entry / "result.json").read_text())


# --------------------------------------------------------------------------------------------------
# Stores: what ran, and whether two runs produced the same outputs (the package is imported inside the
# functions: conftest imports this module, and a run of a few model tests need not import the pipeline)
# --------------------------------------------------------------------------------------------------
def completed_counts(store: Path | Store) -> Counter:
    from navcrafter.schemas.store import Store

    events = (store if isinstance(store, Store) else Store(str(store))).tables.read("steps").to_pylist()
    return Counter((e["scene_id"], e["step"]) for e in events if e["event"] == "completed")


def step_state(store: Path | Store) -> dict[tuple[str, str], tuple[bool, str | None]]:
    """(scene, step) -> (complete, exec_id) of every step group present (a path, or a ``Store`` object,
    e.g. one whose connection is not the run's own)."""
    from navcrafter.schemas.layout import STEPS
    from navcrafter.schemas.store import Store
    from navcrafter.tasks.runner import scene_steps

    s = store if isinstance(store, Store) else Store(str(store))
    out = {}
    for sid in s.scene_ids():
        sc = s.scene(sid)
        for spec, k in [(STEPS["ingest"], None), *[(s.spec, s.k) for s in scene_steps(TINY)]]:
            st = sc.status(spec, k)
            if st.exists:
                out[(sid, st.path)] = (st.complete, st.attrs.get("exec_id"))
    return out


def assert_same_outputs(a: Path, b: Path) -> None:
    """The two stores hold the same arrays and export files for every scene of ``b``, and the same metrics."""
    from navcrafter.schemas.layout import EVALUATE, EXPORT
    from navcrafter.schemas.store import Store
    from navcrafter.tasks.runner import scene_steps

    sa, sb = Store(str(a)), Store(str(b))
    for sid in sb.scene_ids():
        for spec, k in [(s.spec, s.k) for s in scene_steps(TINY)]:
            if spec is EXPORT:
                for name in ("cloud.ply", "trajectory.json", "trajectory.parquet", "video.mp4"):
                    rel = sb.scene(sid).file_rel(EXPORT, None, name)
                    assert sa.read_bytes(rel) == sb.read_bytes(rel), (sid[:8], name)
                continue
            xa, xb = sa.scene(sid).read_all(spec, k), sb.scene(sid).read_all(spec, k)
            assert xa.keys() == xb.keys()
            for name in xa:
                np.testing.assert_array_equal(xa[name], xb[name], err_msg=f"{sid[:8]} {spec.group_path(k)}/{name}")
        ma, mb = (dict(x.scene(sid).status(EVALUATE).attrs["metrics"]) for x in (sa, sb))
        assert {**ma, "plan_seconds": 0} == {**mb, "plan_seconds": 0}, sid[:8]  # all but a timing


def run_cli(args, env_extra, api_url, **kw) -> subprocess.Popen:
    """``navcrafter ARGS`` in a subprocess pointed at the Prefect API ``api_url``."""
    env = {**os.environ, "PREFECT_API_URL": api_url, **env_extra}
    return subprocess.Popen([sys.executable, "-m", "navcrafter.flows.cli", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, **kw)


# --------------------------------------------------------------------------------------------------
# S3 (conftest.s3_endpoint starts moto's S3 server with this bucket)
# --------------------------------------------------------------------------------------------------
BUCKET = "navcrafter-test"


def s3_url(name: str) -> str:
    return f"s3://{BUCKET}/{name}-{uuid.uuid4().hex[:8]}"


# --------------------------------------------------------------------------------------------------
# Real Prefect servers, work pools and workers as processes (test_worker, test_faults)
# --------------------------------------------------------------------------------------------------
POOL = "navcrafter-test"
DEPLOYMENT = "explore-collection/test"
VENV_BIN = str(Path(sys.executable).parent)
UUID = re.compile(r"flow run ([0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12})")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_prefect_server(home: Path, log: Path, port: int | None = None, *, timeout: float = 120,
                         tries: int = 5) -> tuple[subprocess.Popen, int]:
    """``prefect server start`` on SQLite in ``home`` (output to ``log``) on a free port (or ``port``), once it
    answers. The answer must come from *this* server (its ``/admin/settings`` name ``home``): ``free_port``'s port
    can be taken by another process before the server binds it, and then the health check reached that process's
    server (CI, 2026-12-05: test_worker's fixture found its work pool already there). A server that lost its port
    is stopped and started again on another free port, up to ``tries`` times; a fixed ``port`` is not retried."""
    for _ in range(1 if port is not None else tries):
        p = free_port() if port is None else port
        with open(log, "ab") as out:
            proc = subprocess.Popen([f"{VENV_BIN}/prefect", "server", "start", "--host", "127.0.0.1", "--port", str(p)],
                                    env=prefect_env(home, None), stdout=out, stderr=subprocess.STDOUT,
                                    start_new_session=True)
        api, deadline = f"http://127.0.0.1:{p}/api", time.time() + timeout
        while True:
            try:
                answered = api_get(f"{api}/health") is not None
            except OSError:
                answered = False
            if answered:
                try:
                    theirs = api_get(f"{api}/admin/settings").get("home")
                except OSError:
                    theirs = None
                if theirs is not None and Path(theirs).resolve() == Path(home).resolve():
                    return proc, p
                if proc.poll() is not None or theirs is not None:  # another server holds the port
                    kill_tree(proc, signal.SIGTERM)
                    break
            if (not answered and proc.poll() is not None) or time.time() > deadline:
                kill_tree(proc, signal.SIGTERM)
                raise RuntimeError(f"the Prefect server did not start:\n{tail(log)}")
            time.sleep(0.3)
    raise RuntimeError(f"the Prefect server found its port taken by another server {tries if port is None else 1} "
                       f"time(s):\n{tail(log)}")


def prefect_env(home: Path, api_url: str | None) -> dict[str, str]:
    """The environment of a Prefect process with its own PREFECT_HOME (none of this process's PREFECT_*)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(PATH=f"{VENV_BIN}{os.pathsep}{env.get('PATH', '')}", PREFECT_HOME=str(home),
               PREFECT_SERVER_ANALYTICS_ENABLED="false", PREFECT_WORKER_QUERY_SECONDS="1",
               PREFECT_LOGGING_LEVEL="INFO")
    if api_url:
        env["PREFECT_API_URL"] = api_url
    return env


def _descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (Linux /proc; psutil is not a dependency)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    out, todo = [], [pid]
    while todo:
        kids = children.get(todo.pop(), [])
        out += kids
        todo += kids
    return out


def kill_tree(proc: subprocess.Popen, sig: int = signal.SIGKILL) -> None:
    """Kill a process started with start_new_session=True: its group and the groups of its descendants
    (Prefect starts each flow run in a session of its own)."""
    groups = {proc.pid}
    for pid in _descendants(proc.pid):
        try:
            groups.add(os.getpgid(pid))
        except ProcessLookupError:
            pass
    groups.discard(os.getpgrp())
    for pgid in groups:
        try:
            os.killpg(pgid, sig)
        except ProcessLookupError:
            pass
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)


def tail(path: Path, n: int = 4000) -> str:
    return path.read_text(errors="replace")[-n:] if path.exists() else ""


def api_get(url: str, body: dict | None = None):
    """GET ``url``, or POST ``body`` to it as JSON (the API's filter endpoints)."""
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=10) as r:
        return json.loads(r.read())


class Worker:
    """``prefect worker start --pool POOL`` against ``server`` ({"api": URL, "home": PREFECT_HOME})."""

    def __init__(self, server, log: Path, pool: str = POOL) -> None:
        self.log = log
        with open(log, "ab") as out:
            self.proc = subprocess.Popen([f"{VENV_BIN}/prefect", "worker", "start", "--pool", pool],
                                         env=prefect_env(server["home"], server["api"]), stdout=out,
                                         stderr=subprocess.STDOUT, start_new_session=True)

    def kill(self) -> None:
        if self.proc.poll() is None:
            kill_tree(self.proc)


def submit(server, collection: Path, store: Path, *extra: str) -> list[str]:
    """``navcrafter submit`` of ``collection`` to the test deployment; returns the flow run ids it printed."""
    res = subprocess.run([sys.executable, "-m", "navcrafter.flows.cli", "submit", str(collection), "--store",
                          str(store), "--preset", "tiny", "--deployment", DEPLOYMENT, "--work-pool", POOL, *extra],
                         env=prefect_env(server["home"], server["api"]), capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, res.stdout + res.stderr
    ids = UUID.findall(res.stdout)
    assert ids and f"{server['api'].removesuffix('/api')}/runs/flow-run/{ids[0]}" in res.stdout  # dashboard
    return ids


def official_close(got, want) -> float:
    """Largest difference of ``got`` from the official implementation's ``want``, relative to max(1, the reference's
    largest magnitude) (the ``official_parity`` tests' measure; they require <= 1e-4)."""
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    assert got.shape == want.shape, (got.shape, want.shape)
    return float(np.abs(got - want).max() / max(1.0, np.abs(want).max()))
