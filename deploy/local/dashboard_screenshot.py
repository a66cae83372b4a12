"""Screenshot of a scene's flow run in the Prefect dashboard, artifacts tab open (docs/dashboard.png).

    .venv/bin/python deploy/local/dashboard_screenshot.py [--out docs/dashboard.png] [--api-url URL]
        [--flow-run ID] [--runs-out RUNS.png] [--artifact-out DASHBOARD.png] [--kind room] [--json]

Without ``--api-url`` it starts its own ``prefect server start`` (own PREFECT_HOME and SQLite database in a
temporary folder, a free port; stopped at the end). Unless ``--flow-run`` names a run to show, it writes one
demo photo (``--kind``, 320x240) and explores it with ``navcrafter explore --preset tiny`` (simulation mode,
the tests' preset: some seconds) against that server, finds the scene's ``explore-scene`` flow run with the
Prefect client (by its ``scene:<id12>`` and ``store:<hash>`` tags), checks that it published its artifacts
(``progress-<id12>``, ``dashboard-<id12>``, ``plan-<id12>-<k>``, ``scene-<id12>``) and loads
``{ui}/v2/runs/flow-run/<id>?tab=Artifacts`` in headless Chromium. The shot is kept only when the page had
rendered the run's artifact cards (checked in the page's DOM) and is not blank; else it is retried with a
longer wait. ``--runs-out`` adds the flow-runs list (``/runs``), ``--artifact-out`` the scene's dashboard
artifact itself (input, top-down trajectory plots, render grid, metrics; a tall page).

The UI in the browser calls the API URL the server was started with (``PREFECT_UI_API_URL``, else
``http://127.0.0.1:4200/api``): a server started here gets its own; for ``--api-url`` the script checks
``/ui-settings`` and says when the UI would call another address.

Exit status: 0 when every shot was taken and verified, 1 when one failed (the reason is printed), 2 on usage
errors (no chromium, an API that does not answer, a flow run that does not exist).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from uuid import UUID

ROOT = Path(__file__).resolve().parents[2]
MAX_BYTES = 500_000  # a committed PNG stays below this (palette-reduced when larger)


if __package__ in (None, ""):  # run as a script: the repository root makes the deploy package importable
    sys.path.insert(0, str(ROOT))
from deploy.local import browser  # noqa: E402


class UsageError(Exception):
    pass


def _get(url: str, timeout: float = 10.0):
    with urllib.request.urlopen(url, timeout=timeout) as r:
        return json.loads(r.read())


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _prefect_exe() -> str:
    beside = Path(sys.executable).with_name("prefect")
    return str(beside) if beside.is_file() else (shutil.which("prefect") or "prefect")


class Server:
    """``prefect server start`` on a free port with its own PREFECT_HOME; ``stop()`` ends its process group."""

    def __init__(self, home: Path, timeout: float = 180.0) -> None:
        self.home = home
        self.port = _free_port()
        self.api = f"http://127.0.0.1:{self.port}/api"
        self.log = home / "server.log"
        env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
        env.update(PREFECT_HOME=str(home), PREFECT_SERVER_ANALYTICS_ENABLED="false",
                   PREFECT_UI_API_URL=self.api)  # the UI in the browser calls this API (default: port 4200)
        with open(self.log, "wb") as out:
            self.proc = subprocess.Popen([_prefect_exe(), "server", "start", "--host", "127.0.0.1",
                                          "--port", str(self.port)], env=env, stdout=out,
                                         stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + timeout
        while True:
            try:
                _get(f"{self.api}/health", timeout=5)
                return
            except OSError:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    self.stop()
                    raise RuntimeError(f"the Prefect server did not start:\n{self.log.read_text()[-3000:]}") from None
                time.sleep(0.5)

    def stop(self) -> None:
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGTERM)
                self.proc.wait(timeout=20)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                try:
                    os.killpg(self.proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                self.proc.wait(timeout=10)


def ui_base(api: str) -> tuple[str, str]:
    """(the dashboard's URL, the path prefix of its default UI: ``/v2`` on Prefect 3.8) from ``/ui-settings``;
    warns when the UI would call another API than ``api``."""
    ui = api.rstrip("/")
    ui = ui[: -len("/api")] if ui.endswith("/api") else ui
    try:
        settings = _get(f"{ui}/ui-settings")
    except (OSError, ValueError):
        return ui, ""
    ui_api = (settings.get("api_url") or "").rstrip("/")
    if ui_api and ui_api != api.rstrip("/"):
        print(f"warning: the dashboard at {ui} calls the API at {ui_api}, not {api}: its pages stay empty unless "
              f"that answers (start the server with PREFECT_UI_API_URL={api})", file=sys.stderr)
    prefix = settings.get("v2_base_url", "/v2") if settings.get("default_ui") == "v2" else ""
    return ui, prefix.rstrip("/")


def explore_one_scene(api: str, work: Path, kind: str, home: Path | None) -> tuple[str, str]:
    """A demo photo explored with the tiny preset against ``api``; (store path, scene id)."""
    from navcrafter.models.simulation.demo import write_demo_collection
    from navcrafter.schemas.store import Store

    photos, store = work / "photos", work / "store"
    write_demo_collection(photos, (kind,), width=320, height=240, supersample=1)
    env = dict(os.environ)
    if home is not None:  # the server started here: none of the caller's Prefect settings, its PREFECT_HOME
        env = {k: v for k, v in env.items() if not k.startswith("PREFECT_")} | {"PREFECT_HOME": str(home)}
    env.update(PREFECT_API_URL=api, PREFECT_SERVER_ANALYTICS_ENABLED="false", COLUMNS="200")
    t0 = time.monotonic()
    res = subprocess.run([sys.executable, "-m", "navcrafter.flows.cli", "explore", str(photos), "--store", str(store),
                          "--preset", "tiny"], env=env, capture_output=True, text=True, timeout=900)
    if res.returncode != 0:
        raise RuntimeError(f"navcrafter explore exited {res.returncode}:\n{(res.stdout + res.stderr)[-4000:]}")
    [scene_id] = Store(str(store), create=False).scene_ids()
    print(f"explored {kind}-0.png (scene {scene_id[:12]}) in {time.monotonic() - t0:.0f} s")
    return str(store), scene_id


def find_scene_run(store: str, scene_id: str):
    """The scene's latest ``explore-scene`` flow run (found by its tags, as the dashboard filters them)."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowFilter, FlowFilterName, FlowRunFilter, FlowRunFilterTags
    from prefect.client.schemas.sorting import FlowRunSort

    from navcrafter.flows.runstates import scene_run_tags

    with get_client(sync_client=True) as client:
        runs = client.read_flow_runs(
            flow_filter=FlowFilter(name=FlowFilterName(any_=["explore-scene"])),
            flow_run_filter=FlowRunFilter(tags=FlowRunFilterTags(all_=scene_run_tags(store, scene_id))),
            sort=FlowRunSort.START_TIME_DESC, limit=1)
    if not runs:
        raise RuntimeError(f"no explore-scene flow run of scene {scene_id[:12]} on the server")
    return runs[0]


def read_run(flow_run_id: str):
    """(the flow run, its artifacts) from the API."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterFlowRunId
    from prefect.exceptions import ObjectNotFound

    with get_client(sync_client=True) as client:
        try:
            run = client.read_flow_run(UUID(flow_run_id))
        except (ObjectNotFound, ValueError):
            raise UsageError(f"no flow run {flow_run_id} on the server") from None
        arts = client.read_artifacts(
            artifact_filter=ArtifactFilter(flow_run_id=ArtifactFilterFlowRunId(any_=[run.id])))
    return run, arts


def image_problem(png: Path) -> str | None:
    """Why a screenshot looks blank (one colour, a plain background with next to nothing on it), else None."""
    import numpy as np
    from PIL import Image

    px = np.asarray(Image.open(png).convert("RGB"))
    colours = len(np.unique(px.reshape(-1, 3) // 8, axis=0))
    if px.std() < 8 or colours < 32:
        return f"looks blank (pixel std {px.std():.1f}, {colours} colours)"
    return None


def shrink(png: Path, max_bytes: int = MAX_BYTES) -> int:
    """Re-save ``png`` optimised, as a 256-colour palette image when it is larger than ``max_bytes``; its size."""
    from PIL import Image

    img = Image.open(png).convert("RGB")
    buf = io.BytesIO()
    img.save(buf, format="PNG", optimize=True)
    if buf.tell() > max_bytes:
        buf = io.BytesIO()
        img.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(
            buf, format="PNG", optimize=True)
    png.write_bytes(buf.getvalue())
    return len(buf.getvalue())


def shoot(url: str, out: Path, width: int, height: int, wait_ms: int, expect: list[str], tries: int = 3) -> dict:
    """Screenshot ``url`` until the page's DOM holds every string of ``expect`` and the image is not blank
    (each try waits twice as long); raises RuntimeError with the last reason."""
    reason = ""
    for attempt in range(tries):
        t0 = time.monotonic()
        png, dom = browser.screenshot_and_dom(url, out, width, height, wait_ms * 2**attempt,
                                              timeout_s=120 + wait_ms * 2**attempt / 1000)
        missing = [s for s in expect if s not in dom]
        reason = image_problem(png) or (f"the page shows no {', '.join(missing)}" if missing else "")
        if "Can't connect to Server API" in dom:
            reason = "the dashboard could not reach its API (see PREFECT_UI_API_URL)"
        if not reason:
            size = shrink(png)
            print(f"wrote {out} ({size / 1000:.0f} kB, {time.monotonic() - t0:.0f} s): {url}")
            return {"path": str(out), "url": url, "bytes": size}
        print(f"try {attempt + 1}: {url} {reason}", file=sys.stderr)
    raise RuntimeError(f"no usable screenshot of {url}: {reason}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "dashboard.png",
                   help="the flow run's page, artifacts tab (default: docs/dashboard.png)")
    p.add_argument("--api-url", help="a running Prefect server's API (default: start one here)")
    p.add_argument("--flow-run", help="show this flow run (default: explore a demo scene and show its run)")
    p.add_argument("--runs-out", type=Path, help="also the flow-runs list, to this PNG")
    p.add_argument("--artifact-out", type=Path, help="also the scene's dashboard artifact, to this PNG")
    p.add_argument("--kind", default="room", choices=("room", "street", "tabletop"), help="demo scene kind")
    p.add_argument("--width", type=int, default=1400)
    p.add_argument("--height", type=int, default=1000)
    p.add_argument("--artifact-height", type=int, default=2600, help="window height of --artifact-out")
    p.add_argument("--wait-ms", type=int, default=20000, help="Chromium's virtual-time budget per page")
    p.add_argument("--work", type=Path, help="keep the demo photo and store here (default: a temporary folder)")
    p.add_argument("--json", action="store_true", help="print a JSON summary as the last line")
    args = p.parse_args(argv)

    if browser.find_chromium() is None:
        print("no chromium found: apt-get install chromium (or set CHROMIUM=/path/to/chrome)", file=sys.stderr)
        return 2
    tmp = Path(tempfile.mkdtemp(prefix="navcrafter-dashboard-"))
    work = args.work or tmp
    work.mkdir(parents=True, exist_ok=True)
    server = None
    try:
        if args.api_url:
            api, home = args.api_url.rstrip("/"), None
            try:
                _get(f"{api}/health")
            except (OSError, ValueError) as exc:
                raise UsageError(f"the Prefect API at {api} does not answer: {exc}") from None
        else:
            home = tmp / "prefect-home"
            home.mkdir()
            t0 = time.monotonic()
            server = Server(home)
            api = server.api
            print(f"started prefect server start on {api} in {time.monotonic() - t0:.0f} s")
        os.environ["PREFECT_API_URL"] = api  # this process's Prefect client
        if home is not None:
            os.environ["PREFECT_HOME"] = str(home)

        if args.flow_run:
            flow_run_id = args.flow_run
        else:
            store, scene_id = explore_one_scene(api, work / "demo", args.kind, home)
            flow_run_id = str(find_scene_run(store, scene_id).id)
        run, arts = read_run(flow_run_id)
        keys = sorted(a.key for a in arts if a.key)
        print(f"flow run {run.name} ({run.id}), {run.state_type.value if run.state_type else '?'}; "
              f"artifacts: {', '.join(keys) or 'none'}")
        if run.name.startswith("scene-"):
            short = run.name.removeprefix("scene-")
            wanted = {f"progress-{short}", f"dashboard-{short}"}
            if not wanted <= set(keys):
                raise RuntimeError(f"the scene run lacks the artifacts {', '.join(sorted(wanted - set(keys)))}")
        ui, prefix = ui_base(api)
        page = f"{ui}{prefix}/runs/flow-run/{run.id}?tab=Artifacts"
        shots = {"flow_run": shoot(page, args.out, args.width, args.height, args.wait_ms, [run.name, *keys])}
        if args.runs_out:
            shots["runs"] = shoot(f"{ui}{prefix}/runs", args.runs_out, args.width, args.height, args.wait_ms,
                                  [run.name])
        dashboard = next((a for a in arts if (a.key or "").startswith("dashboard-")), None)
        if args.artifact_out and dashboard is not None:
            shots["artifact"] = shoot(f"{ui}{prefix}/artifacts/artifact/{dashboard.id}", args.artifact_out,
                                      args.width, args.artifact_height, args.wait_ms, [dashboard.key, "Metrics"])
        if args.json:
            print(json.dumps({"api_url": api, "ui_url": ui, "flow_run_id": str(run.id), "flow_run_name": run.name,
                              "state": run.state_type.value if run.state_type else None, "artifacts": keys,
                              "shots": shots}))
        return 0
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        if server is not None:
            server.stop()
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
