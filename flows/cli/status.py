"""``navcrafter status``: the store's manifest beside the Prefect state of each scene's flow run."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from navcrafter.flows.cli.options import console, usage_errors


def status(
    store: Annotated[str, typer.Argument(help="Store directory or URL.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the manifest as JSON lines.")] = False,
    compact: Annotated[bool, typer.Option(help="Merge the store's table files first.")] = False,
    api_url: Annotated[Optional[str], typer.Option(
        help="Prefect API to read the runs' states from (default: PREFECT_API_URL).")] = None,
    no_progress_after: Annotated[float, typer.Option(
        min=1, help="Seconds without a finished step before a RUNNING scene is flagged.")] = 1800.0,
) -> None:
    """Show the manifest (one row per image: status, last step, metrics, error) beside the Prefect
    state of its flow run, and flag scenes that need action (stale, possibly dead worker)."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.flows.runstates import run_states
    from navcrafter.flows.tools.report import read_manifest
    from navcrafter.schemas.store import Store, StoreError

    with usage_errors(StoreError):
        st = Store(store, create=False)
    if compact:
        for name in ("manifest", "steps", "metrics", "evaluations"):
            st.tables.compact(name)
    rows = read_manifest(st).to_pylist()
    states = run_states(st, rows, api_url, no_progress_after=no_progress_after)
    if as_json:
        for r, s in zip(rows, states.scenes):
            r["updated_at"] = r["updated_at"].isoformat()
            r["timings"] = dict(r["timings"] or [])
            r["metrics"] = dict(r["metrics"] or [])
            run = s.run
            r.update({"prefect_api": "reachable" if states.reachable else "unknown",
                      "prefect_state": s.prefect_state, "prefect_state_name": run.state_name if run else None,
                      "prefect_flow_run_id": run.id if run else None,
                      "prefect_flow_run_name": run.name if run else None,
                      "prefect_collection_state": s.collection_run.state if s.collection_run else None,
                      "last_progress_at": s.last_progress.isoformat() if s.last_progress else None,
                      "issue": s.issue, "advice": s.advice})
            print(json.dumps(r))
        return
    if not rows:
        console.print(f"{store}: no images yet")
        return
    table = Table(title=f"navcrafter store {store}")
    columns = ["image", "scene", "status", "prefect", "step", "backend", "points", "median dist.", "seconds", "error"]
    if not states.reachable:
        columns.remove("prefect")
    for col in columns:
        table.add_column(col, overflow="fold")
    for r, s in zip(rows, states.scenes):
        metrics = dict(r["metrics"] or [])
        med = metrics.get("cloud_median_dist_m")
        colour = {"done": "green", "failed": "red", "running": "yellow"}.get(r["status"], "")
        prefect = []
        if states.reachable:
            state = (s.run.state_name or s.run.state or "?") if s.run else "not found"
            prefect = [f"[red]{state} ({s.issue})[/red]" if s.issue else state]
        table.add_row(Path(r["source"]).name, (r["scene_id"] or "")[:12], f"[{colour}]{r['status']}[/{colour}]",
                      *prefect, r["step"] or "", r["backend"] or "",
                      "" if r["n_points"] is None else str(r["n_points"]), "" if med is None else f"{med:.4f} m",
                      f"{r['seconds'] or 0:.1f}", r["error"] or "")
    console.print(table)
    if any(r["backend"] == "simulation" for r in rows):
        # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
        from navcrafter.models.simulation import LABEL

        console.print(f"[yellow]backend 'simulation': {LABEL}.[/yellow]")
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "running", "failed", "pending")}
    console.print(", ".join(f"{v} {k}" for k, v in counts.items() if v))
    if not states.reachable:
        console.print(f"Prefect state: unknown ({states.error}); the table shows the store's manifest only.")
    for s in states.issues:
        console.print(f"[red]{Path(s.source).name} ({(s.scene_id or '')[:12]}): {s.issue}[/red]: {s.advice}")
