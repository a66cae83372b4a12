"""``navcrafter view``: a 3D viewer of a store's explored scenes in the browser (viser; ``flows/tools/viewer.py``)."""

from __future__ import annotations

import os
import signal
import sys
import threading
from typing import Annotated, Optional

import typer

from navcrafter.flows.cli.options import console, fail


def view(
    store: Annotated[str, typer.Argument(help="Store directory or URL.")],
    scene: Annotated[Optional[str], typer.Argument(
        help="Scene id (or a unique prefix) or source file name; default: the first scene.")] = None,
    port: Annotated[int, typer.Option(min=1, max=65535, help="Port of the viewer (the next free one if taken).")
                    ] = 8080,
    host: Annotated[str, typer.Option(help="Address to listen on (0.0.0.0: every interface).")] = "127.0.0.1",
) -> None:
    """Serve a 3D viewer of a scene: its fitted Gaussians (when the fit ran), the fused cloud per iteration, the
    input photo, planned and estimated cameras, the plan's candidates (rejected by the collision detector G or
    not) and the video frames; a dropdown switches between the store's scenes. Serves until Ctrl-C."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.flows.tools.viewer import NO_FIT, build_viewer
    from navcrafter.schemas.store import Store, StoreError
    from navcrafter.tasks.readers import SceneNotFound, resolve_scene

    try:
        st = Store(store, create=False)
        sid = resolve_scene(st, scene, default="first")
    except StoreError as exc:
        fail(str(exc), "(`navcrafter status STORE` lists the scenes of a store)")
    except SceneNotFound as exc:
        fail(str(exc))
    import viser

    server = viser.ViserServer(host=host, port=port, verbose=False)
    stop = stop_signal()
    try:
        viewer = build_viewer(server, st, sid)
        data = viewer.view.data
        if data.label:
            console.print(f"[yellow]{data.label}[/yellow]", soft_wrap=True)
        if data.gaussians is None:
            console.print(f"[yellow]scene {sid[:12]}: {NO_FIT}[/yellow]", soft_wrap=True)
        shown = "localhost" if host in ("0.0.0.0", "::") else host
        console.print(f"navcrafter view: scene {sid[:12]} of {store} at http://{shown}:{server.get_port()} "
                      "(Ctrl-C to stop)", soft_wrap=True)
    except BaseException:
        stop_server(server)
        raise
    while not stop.wait(0.5):  # a timed wait: the signal handlers run in the main thread between waits
        pass
    console.print("navcrafter view: stopped")
    stop_server(server)
    # The viewer writes nothing, so nothing is lost by ending the process here, and it must end here: viser runs
    # client callbacks on a ThreadPoolExecutor whose worker threads are not daemons and are joined at interpreter
    # exit, so one callback that never returns (a client's message handled while its connection closes) kept
    # `navcrafter view` alive after Ctrl-C for ever (tests/flows/tools/test_viewer.py reproduces it with a blocked
    # worker).
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(0)


def stop_signal() -> threading.Event:
    """An event set by SIGINT (Ctrl-C) or SIGTERM."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def stop_server(server, timeout_s: float = 10.0) -> None:
    """Stop a viser server, waiting at most ``timeout_s`` for it (its own joins are bounded; this bounds the rest)."""
    stopper = threading.Thread(target=server.stop, daemon=True)
    stopper.start()
    stopper.join(timeout_s)
