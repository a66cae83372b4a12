"""``navcrafter view``: a 3D viewer of a store's explored scenes in the browser (viser; ``flows/tools/viewer.py``)."""

from __future__ import annotations

import time
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
    from navcrafter.flows.tools.viewer import NO_FIT, SceneNotFound, build_viewer, resolve_scene
    from navcrafter.schemas.store import Store, StoreError

    try:
        st = Store(store, create=False)
        sid = resolve_scene(st, scene)
    except StoreError as exc:
        fail(str(exc), "(`navcrafter status STORE` lists the scenes of a store)")
    except SceneNotFound as exc:
        fail(str(exc))
    import viser

    server = viser.ViserServer(host=host, port=port, verbose=False)
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
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        console.print("navcrafter view: stopped")
    finally:
        server.stop()
