"""The ``navcrafter`` command line."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer
import yaml
from rich.console import Console
from rich.markdown import Markdown
from rich.table import Table

app = typer.Typer(help="NavCrafter: explore 3D scenes from single images, as a resumable batch workflow.",
                  no_args_is_help=True, add_completion=False)
# Wide when piped (logs, CI): rich would otherwise fold the summary table into 80 columns.
console = Console(width=None if sys.stdout.isatty() else 160)
err = Console(stderr=True, width=None if sys.stderr.isatty() else 160)

from navcrafter.flows.models_cli import models_app  # noqa: E402

app.add_typer(models_app, name="models")

EXIT_USAGE = 2
EXIT_PARTIAL = 3


def _prefect_env() -> None:
    """Offline-friendly Prefect defaults (each can be overridden from the environment)."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_LOGGING_EXTRA_LOGGERS", "navcrafter")
    # The temporary local server needs longer than Prefect's 20 s default on a busy 2-core machine.
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "90")


def _parse_sets(values: list[str]) -> dict:
    out = {}
    for item in values:
        if "=" not in item:
            raise typer.BadParameter(f"--set expects KEY=VALUE (e.g. synthesis.num_frames=9), got {item!r}")
        key, value = item.split("=", 1)
        out[key.strip()] = yaml.safe_load(value)
    return out


@app.command("demo-data")
def demo_data(
    folder: Annotated[Path, typer.Argument(help="Folder to write the demo photos into.")],
    kinds: Annotated[str, typer.Option(help="Comma-separated scene kinds: room, street, tabletop.")] =
        "room,street,tabletop",
    per_kind: Annotated[int, typer.Option(min=1, help="Photos (different seeds) per kind.")] = 1,
    seed: Annotated[int, typer.Option(help="First generator seed.")] = 0,
    width: Annotated[int, typer.Option(min=64)] = 640,
    height: Annotated[int, typer.Option(min=64)] = 480,
) -> None:
    """Write a demo collection: photo-like renders of generated scenes, with hidden ground truth."""
    from navcrafter.models.simulation.demo import write_demo_collection
    from navcrafter.models.simulation.scenes import KINDS

    chosen = tuple(k.strip() for k in kinds.split(",") if k.strip())
    bad = [k for k in chosen if k not in KINDS]
    if bad:
        err.print(f"[red]unknown scene kind(s) {bad}; choose from {list(KINDS)}[/red]")
        raise typer.Exit(EXIT_USAGE)
    photos = write_demo_collection(folder, chosen, per_kind, seed, width, height)
    console.print(f"wrote {len(photos)} demo photos to {folder} (ground truth in {folder}/.groundtruth/)")
    for p in photos:
        console.print(f"  {p}")


def _load_config(path: Optional[Path], preset: str, overrides: dict):
    from pydantic import ValidationError

    from navcrafter.schemas.config import RunConfig

    try:
        return RunConfig.load(path, preset=preset, overrides=overrides)
    except (ValidationError, ValueError, FileNotFoundError) as exc:
        err.print(f"[red]invalid configuration:[/red] {exc}")
        raise typer.Exit(EXIT_USAGE) from None


@app.command()
def explore(
    photos: Annotated[str, typer.Argument(
        help="A folder of images (searched recursively), one image, or an fsspec URL prefix (s3://bucket/photos/).")],
    store: Annotated[str, typer.Option("--store", help="Store directory (or fsspec URL) for all outputs.")],
    preset: Annotated[str, typer.Option(help="Config preset: 'paper' (defaults of the paper) or 'tiny'.")] =
        "paper",
    config: Annotated[Optional[Path], typer.Option(help="YAML/JSON config file applied over the preset.")] = None,
    set_: Annotated[Optional[list[str]], typer.Option("--set", help="Override, e.g. --set lift.max_views=8.")] = None,
    backend: Annotated[Optional[str], typer.Option(help="'simulation' or 'onnx'.")] = None,
    models: Annotated[Optional[Path], typer.Option(help="Directory of exported ONNX models.")] = None,
    parallel: Annotated[Optional[int], typer.Option(min=1, help="Scenes processed at once.")] = None,
    scene_deployment: Annotated[Optional[str], typer.Option(
        help="Run each scene as a flow run of this deployment (e.g. explore-scene/NAME on a GPU work pool; "
             "needs PREFECT_API_URL) instead of in this process.")] = None,
) -> None:
    """Explore every image: geometry, N x (plan, synthesize, lift), export. Reruns resume."""
    from navcrafter.models.simulation import LABEL

    overrides = _parse_sets(set_ or [])
    if backend is not None:
        overrides["backend"] = backend
    if models is not None:
        overrides["model_dir"] = str(models)
    if parallel is not None:
        overrides["max_parallel_scenes"] = parallel
    cfg = _load_config(config, preset, overrides)
    if "://" in photos:
        from navcrafter.tasks.ingest import CollectionError, list_collection

        try:
            list_collection(photos)
        except CollectionError as exc:
            err.print(f"[red]{exc}[/red]")
            raise typer.Exit(EXIT_USAGE) from None
    elif not Path(photos).exists():
        err.print(f"[red]{photos} does not exist[/red]; make a demo collection with "
                  f"`navcrafter demo-data {photos}`")
        raise typer.Exit(EXIT_USAGE)
    if cfg.backend == "simulation":
        console.print(f"[bold yellow]{LABEL}.[/bold yellow]")
    elif cfg.backend == "onnx" and cfg.model_dir is not None and Path(cfg.model_dir).is_dir():
        from navcrafter.models.backends import run_label

        if label := run_label(cfg):
            console.print(f"[bold yellow]{label}.[/bold yellow]")
    _prefect_env()
    from prefect.task_runners import ThreadPoolTaskRunner

    from navcrafter.flows.explore import explore_collection, preflight

    problems = preflight(cfg)
    if problems:
        for p in problems:
            err.print(f"[red]{p}[/red]")
        raise typer.Exit(EXIT_USAGE)
    if scene_deployment:  # scene runs go to workers elsewhere: they need a server they can reach
        from navcrafter.flows.dispatch import DispatchError, check_scene_deployment
        from navcrafter.flows.submit import SubmitError, require_server

        try:
            require_server()
            check_scene_deployment(scene_deployment)
        except (SubmitError, DispatchError) as exc:
            err.print(f"[red]{exc}[/red]")
            raise typer.Exit(EXIT_USAGE) from None

    flow_ = explore_collection.with_options(task_runner=ThreadPoolTaskRunner(max_workers=cfg.max_parallel_scenes))
    run = flow_(photos, store, cfg, scene_deployment=scene_deployment)
    results = run.scenes
    from navcrafter.tasks.report import EXPORT_FILES, SUMMARY_COLUMNS, summary_header, summary_rows

    table = Table(title="navcrafter run summary")
    columns = (*SUMMARY_COLUMNS[:4], "median dist.", "cover.", "noise", "F", "coll.", "sec", "error")
    for col in columns:
        table.add_column(col, overflow="fold")
    for row in summary_rows(results):
        table.add_row(*row[:-1], row[-1] if row[2] != "done" else "")
    console.print(table)
    for line in summary_header(run.run_id, cfg, results):
        console.print(line)
    console.print(f"outputs: {store}/scenes/<scene id>/exports/ ({EXPORT_FILES})")
    failed = [r for r in results if r.status != "done"]
    if run.summary:
        console.print(f"summary: {store}/{run.summary}   status: navcrafter status {store}")
    for note in run.store_errors:  # the store was down or full: the table above is all there is
        err.print(f"[yellow]{note}[/yellow]")
    if failed:
        err.print(f"[red]{len(failed)} of {len(results)} images failed[/red] (see the error column); "
                  f"completed work is kept, rerun the same command to retry.")
        raise typer.Exit(EXIT_PARTIAL)


@app.command()
def evaluate(
    store: Annotated[str, typer.Argument(help="Store directory or URL of explored scenes.")],
    preset: Annotated[str, typer.Option(help="Config preset the scenes were explored with.")] = "paper",
    config: Annotated[Optional[Path], typer.Option(help="YAML/JSON config file applied over the preset.")] = None,
    set_: Annotated[Optional[list[str]], typer.Option(
        "--set", help="Override, e.g. --set evaluation.pose_frames=20.")] = None,
    eval_weights: Annotated[Optional[Path], typer.Option(
        help="Folder of official evaluation weights (LPIPS, FID Inception, FVD I3D).")] = None,
    parallel: Annotated[Optional[int], typer.Option(min=1, help="Scenes scored at once.")] = None,
) -> None:
    """Score every finished scene: the paper's Tables III-VII as Parquet and Markdown in the store."""
    from navcrafter.schemas.store import Store, StoreError

    overrides = _parse_sets(set_ or [])
    if eval_weights is not None:
        overrides["evaluation.weights_dir"] = str(eval_weights)
    if parallel is not None:
        overrides["max_parallel_scenes"] = parallel
    cfg = _load_config(config, preset, overrides)
    try:
        Store(store, create=False)
    except StoreError as exc:
        err.print(f"[red]{exc}[/red]")
        raise typer.Exit(EXIT_USAGE) from None
    _prefect_env()
    from navcrafter.flows.evaluate import evaluable_scenes, evaluate_store_local

    if not evaluable_scenes(store)[0]:
        err.print(f"[red]{store} has no finished scenes[/red]; run `navcrafter explore PHOTOS --store {store}` first")
        raise typer.Exit(EXIT_USAGE)
    result = evaluate_store_local(store, cfg)
    console.print(Markdown(Store(store, create=False).read_bytes(result.report).decode()))
    console.print(f"report: {store}/{result.report}   table: {store}/tables/evaluations/{result.evaluation_id}.parquet")
    if result.failed:
        err.print(f"[red]{len(result.failed)} scene(s) could not be scored[/red]: "
                  + "; ".join(f"{k[:12]}: {v}" for k, v in result.failed.items()))
        raise typer.Exit(EXIT_PARTIAL)


@app.command("dataset-clips")
def dataset_clips(
    kind: Annotated[str, typer.Argument(help="'re10k', 'dl3dv' or 'tnt'.")],
    root: Annotated[Path, typer.Argument(help="The dataset's folder (layouts: schemas/datasets.py).")],
    out: Annotated[Path, typer.Option("--out", help="Folder for the clips.")],
    clips: Annotated[Optional[int], typer.Option(help="Clips to draw (default: one per sequence).")] = None,
    frames: Annotated[int, typer.Option(help="Frames after the conditioning image (paper: 14).")] = 14,
    resolution: Annotated[int, typer.Option(help="Square size the frames are resized/cropped to.")] = 256,
    seed: Annotated[int, typer.Option(help="Seed of the clip draw.")] = 0,
) -> None:
    """Write benchmark clips (conditioning image, reference frames, cameras) for a video generator."""
    from navcrafter.schemas.datasets import DatasetError, open_dataset
    from navcrafter.tasks.clips import export_clips

    if not root.is_dir():
        err.print(f"[red]{root} is not a folder[/red]; give the dataset's root folder")
        raise typer.Exit(EXIT_USAGE)
    try:
        reader = open_dataset(kind, root, num_frames=frames, clips_per_dataset=clips, seed=seed,
                              resolution=resolution)
        keys = export_clips(reader, out)
    except (DatasetError, ValueError, FileNotFoundError) as exc:
        err.print(f"[red]{exc}[/red]")
        raise typer.Exit(EXIT_USAGE) from None
    console.print(f"wrote {len(keys)} clips to {out}")
    for name, reason in reader.skipped.items():
        err.print(f"[yellow]skipped {name}[/yellow]: {reason}")


@app.command("evaluate-clips")
def evaluate_clips_cmd(
    clips: Annotated[Path, typer.Argument(help="Clips written by `navcrafter dataset-clips`.")],
    generated: Annotated[Path, typer.Argument(help="Generated frames: GENERATED/<clip>/0001.png ...")],
    out: Annotated[Path, typer.Option("--out", help="Folder for evaluations.parquet and report.md.")],
    eval_weights: Annotated[Optional[Path], typer.Option(
        help="Folder of official evaluation weights (LPIPS, FID Inception, FVD I3D).")] = None,
    camera_guidance: Annotated[bool, typer.Option(help="Run COLMAP for R_err/T_err.")] = True,
) -> None:
    """Score generated clips against their dataset clips: PSNR/SSIM/LPIPS, R_err/T_err, FID/FVD."""
    from navcrafter.schemas.config import EvaluationConfig

    cfg = EvaluationConfig(weights_dir=eval_weights, camera_guidance=camera_guidance)
    from navcrafter.tasks.clips import clip_keys

    try:
        clip_keys(clips)
    except FileNotFoundError as exc:
        err.print(f"[red]{exc}[/red]")
        raise typer.Exit(EXIT_USAGE) from None
    if not generated.is_dir():
        err.print(f"[red]{generated} is not a folder[/red] of generated clips (GENERATED/<clip>/0001.png ...)")
        raise typer.Exit(EXIT_USAGE)
    _prefect_env()
    from navcrafter.flows.evaluate import evaluate_clips

    result = evaluate_clips(str(clips), str(generated), str(out), cfg)
    console.print(Markdown(Path(result.report).read_text()))
    console.print(f"report: {result.report}   table: {out}/evaluations.parquet")
    if result.failed:
        err.print(f"[red]{len(result.failed)} clip(s) could not be scored[/red]: "
                  + "; ".join(f"{k}: {v}" for k, v in result.failed.items()))
        raise typer.Exit(EXIT_PARTIAL)


@app.command()
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
    from navcrafter.flows.runstates import run_states
    from navcrafter.schemas.store import Store, StoreError
    from navcrafter.tasks.report import read_manifest

    try:
        st = Store(store, create=False)
    except StoreError as exc:
        err.print(f"[red]{exc}[/red]")
        raise typer.Exit(EXIT_USAGE) from None
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
        from navcrafter.models.simulation import LABEL

        console.print(f"[yellow]backend 'simulation': {LABEL}.[/yellow]")
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "running", "failed", "pending")}
    console.print(", ".join(f"{v} {k}" for k, v in counts.items() if v))
    if not states.reachable:
        console.print(f"Prefect state: unknown ({states.error}); the table shows the store's manifest only.")
    for s in states.issues:
        console.print(f"[red]{Path(s.source).name} ({(s.scene_id or '')[:12]}): {s.issue}[/red]: {s.advice}")


@app.command()
def submit(
    collection: Annotated[str, typer.Argument(
        help="A folder of images, one image, a list file (.txt/.lst/.list: one image path per line), or an "
             "fsspec URL prefix (s3://bucket/photos/).")],
    store: Annotated[str, typer.Option("--store", help="Store directory (or fsspec URL) the workers write to.")],
    deployment: Annotated[str, typer.Option(help="Deployment 'flow/name' to create runs of.")] =
        "explore-collection/default",
    per_image: Annotated[bool, typer.Option("--per-image", help="One flow run per image (list files always).")] =
        False,
    tag: Annotated[Optional[list[str]], typer.Option("--tag", help="Tag for the flow runs (repeatable).")] = None,
    work_pool: Annotated[Optional[str], typer.Option(
        help="First create/update the deployment from this checkout on this process work pool.")] = None,
    scene_deployment: Annotated[Optional[str], typer.Option(
        help="The runs start each scene as a flow run of this deployment (explore-scene/NAME).")] = None,
    scene_pool: Annotated[Optional[str], typer.Option(
        help="First create/update explore-scene/NAME (NAME: --scene-deployment's, else --deployment's) from "
             "this checkout on this process work pool (e.g. GPU machines' workers), and dispatch scenes to it.")] =
        None,
    preset: Annotated[str, typer.Option(help="Config preset: 'paper' (defaults of the paper) or 'tiny'.")] =
        "paper",
    config: Annotated[Optional[Path], typer.Option(help="YAML/JSON config file applied over the preset.")] = None,
    set_: Annotated[Optional[list[str]], typer.Option("--set", help="Override, e.g. --set lift.max_views=8.")] = None,
) -> None:
    """Submit a collection to a Prefect deployment (workers explore it); prints the flow-run ids."""
    cfg = _load_config(config, preset, _parse_sets(set_ or []))
    _prefect_env()
    from navcrafter.flows.submit import (
        SCENE_ENTRYPOINT,
        SCENE_FLOW_NAME,
        SubmitError,
        absolute,
        collection_items,
        deploy_local,
        require_server,
        submit_collection,
        ui_url,
    )

    try:  # usage errors first, before the (slow) flow imports
        collection_items(collection, per_image)
        require_server()
    except SubmitError as exc:
        err.print(f"[red]{exc}[/red]")
        raise typer.Exit(EXIT_USAGE) from None
    from navcrafter.flows.explore import preflight

    problems = preflight(cfg)
    if problems:
        for p in problems:
            err.print(f"[red]{p}[/red]")
        raise typer.Exit(EXIT_USAGE)
    try:
        if work_pool:
            flow_name, _, name = deployment.partition("/")
            if flow_name != "explore-collection" or not name:
                err.print(f"[red]--work-pool deploys 'explore-collection/NAME'; got --deployment {deployment!r}[/red]")
                raise typer.Exit(EXIT_USAGE)
            dep_id = deploy_local(work_pool, name=name)
            console.print(f"deployment {deployment} ({dep_id}) on work pool {work_pool}")
        if scene_pool:
            scene_dep = scene_deployment or f"{SCENE_FLOW_NAME}/{deployment.partition('/')[2] or 'default'}"
            flow_name, _, name = scene_dep.partition("/")
            if flow_name != SCENE_FLOW_NAME or not name:
                err.print(f"[red]--scene-pool deploys '{SCENE_FLOW_NAME}/NAME'; got --scene-deployment "
                          f"{scene_deployment!r}[/red]")
                raise typer.Exit(EXIT_USAGE)
            dep_id = deploy_local(scene_pool, name=name, entrypoint=SCENE_ENTRYPOINT)
            console.print(f"deployment {scene_dep} ({dep_id}) on work pool {scene_pool}: scenes run there")
            scene_deployment = scene_dep
        sub = submit_collection(collection, store, cfg, deployment=deployment, per_image=per_image, tags=tag or [],
                                scene_deployment=scene_deployment)
    except SubmitError as exc:
        err.print(f"[red]{exc}[/red]")
        raise typer.Exit(EXIT_USAGE) from None
    ui = ui_url()
    console.print(f"submitted {len(sub.flow_run_ids)} flow run(s) of {sub.deployment}:")
    for run_id, name, photos in zip(sub.flow_run_ids, sub.names, sub.photos):
        print(f"flow run {run_id} ({name}): {photos}")  # plain print: one line each, easy to parse
    console.print("watch them:")
    if ui:
        for run_id in sub.flow_run_ids[:5]:
            console.print(f"  {ui}/runs/flow-run/{run_id}")
        if len(sub.flow_run_ids) > 5:
            console.print(f"  ... all runs: {ui}/runs")
    console.print(f"  prefect flow-run inspect {sub.flow_run_ids[0]}")
    console.print(f"  navcrafter status {absolute(store)}")
    console.print("Runs wait for a worker: `prefect worker start --pool POOL` on a machine with navcrafter "
                  "installed. A killed run is finished by submitting the collection again (completed steps "
                  "are kept).")


def main() -> None:
    _prefect_env()
    app()


if __name__ == "__main__":
    sys.exit(main())
