"""``navcrafter explore`` (run a collection in this process) and ``navcrafter submit`` (hand it to workers)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer
from rich.table import Table

from navcrafter.flows.cli.options import (
    EXIT_PARTIAL,
    ConfigOption,
    PresetOption,
    SetOption,
    console,
    err,
    fail,
    prefect_env,
    run_config,
    usage_errors,
)

if TYPE_CHECKING:
    from navcrafter.schemas.config import RunConfig


def _refuse_problems(cfg: RunConfig) -> None:
    """What the config asks for that is not built yet or cannot work ends the command before any work."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.flows.explore import preflight

    if problems := preflight(cfg):
        fail(*problems)


def explore(
    photos: Annotated[str, typer.Argument(
        help="A folder of images (searched recursively), one image, or an fsspec URL prefix (s3://bucket/photos/).")],
    store: Annotated[str, typer.Option("--store", help="Store directory (or fsspec URL) for all outputs.")],
    preset: PresetOption = "paper",
    config: ConfigOption = None,
    set_: SetOption = None,
    backend: Annotated[Optional[str], typer.Option(help="'simulation' or 'onnx'.")] = None,
    models: Annotated[Optional[Path], typer.Option(help="Directory of exported ONNX models.")] = None,
    parallel: Annotated[Optional[int], typer.Option(min=1, help="Scenes processed at once.")] = None,
    scene_deployment: Annotated[Optional[str], typer.Option(
        help="Run each scene as a flow run of this deployment (e.g. explore-scene/NAME on a GPU work pool; "
             "needs PREFECT_API_URL) instead of in this process.")] = None,
    trajectory: Annotated[Optional[list[str]], typer.Option(
        "--trajectory", help="Replace the planner: a preset NAME[:SIZE] (orbit, arc, dolly, pan, tilt, truck, "
        "pedestal, spiral, lookaround) or a camera file (.txt RealEstate10K, transforms.json, camera_path.json, "
        ".npy/.json c2w matrices); repeat it for one entry per iteration (plan.trajectory).")] = None,
) -> None:
    """Explore every image: geometry, N x (plan, synthesize, lift), export. Reruns resume."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.simulation import GROUNDTRUTH_DIR, simulation_label

    cfg = run_config(preset, config, set_, {"backend": backend, "model_dir": str(models) if models else None,
                                            "max_parallel_scenes": parallel, "plan.trajectory": trajectory})
    if "://" in photos:
        # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
        from navcrafter.tasks.ingest import CollectionError, list_collection

        with usage_errors(CollectionError):
            list_collection(photos)
    elif not Path(photos).exists():
        fail(f"{photos} does not exist; make a demo collection with `navcrafter demo-data {photos}`")
    if cfg.backend == "simulation":  # the labels of the demo's scenes (generated, or scans: demo-data --world)
        specs = []
        for p in [] if "://" in photos else Path(photos).glob(f"{GROUNDTRUTH_DIR}/*/scene.json"):
            try:
                specs.append(json.loads(p.read_text()).get("scene"))
            except (OSError, ValueError):  # ingest reports an unreadable truth record with its fix
                continue
        for label in dict.fromkeys(simulation_label(s) for s in specs or [None]):
            console.print(f"[bold yellow]{label}.[/bold yellow]")
    elif cfg.backend == "onnx" and cfg.model_dir is not None and Path(cfg.model_dir).is_dir():
        # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
        from navcrafter.tasks.backends import run_label

        if label := run_label(cfg):
            console.print(f"[bold yellow]{label}.[/bold yellow]")
    prefect_env()
    from prefect.task_runners import ThreadPoolTaskRunner

    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.flows.explore import explore_collection

    _refuse_problems(cfg)
    if scene_deployment:  # scene runs go to workers elsewhere: they need a server they can reach
        # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
        from navcrafter.flows.dispatch import DispatchError, check_scene_deployment
        from navcrafter.flows.submit import SubmitError, require_server

        with usage_errors(SubmitError, DispatchError):
            require_server()
            check_scene_deployment(scene_deployment)

    flow_ = explore_collection.with_options(task_runner=ThreadPoolTaskRunner(max_workers=cfg.max_parallel_scenes))
    run = flow_(photos, store, cfg, scene_deployment=scene_deployment)
    results = run.scenes
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.flows.tools.report import EXPORT_FILES, SUMMARY_COLUMNS, summary_header, summary_rows

    table = Table(title="navcrafter run summary")
    columns = (*SUMMARY_COLUMNS[:4], "median dist.", "seen", "cover.", "cov. 5cm", "noise", "F", "coll.", "3DGS", "sec",
               "error")
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
    preset: PresetOption = "paper",
    config: ConfigOption = None,
    set_: SetOption = None,
) -> None:
    """Submit a collection to a Prefect deployment (workers explore it); prints the flow-run ids."""
    cfg = run_config(preset, config, set_)
    prefect_env()
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
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

    with usage_errors(SubmitError):  # usage errors first, before the (slow) flow imports
        collection_items(collection, per_image)
        require_server()
    _refuse_problems(cfg)
    with usage_errors(SubmitError):
        if work_pool:
            flow_name, _, name = deployment.partition("/")
            if flow_name != "explore-collection" or not name:
                fail(f"--work-pool deploys 'explore-collection/NAME'; got --deployment {deployment!r}")
            dep_id = deploy_local(work_pool, name=name)
            console.print(f"deployment {deployment} ({dep_id}) on work pool {work_pool}")
        if scene_pool:
            scene_dep = scene_deployment or f"{SCENE_FLOW_NAME}/{deployment.partition('/')[2] or 'default'}"
            flow_name, _, name = scene_dep.partition("/")
            if flow_name != SCENE_FLOW_NAME or not name:
                fail(f"--scene-pool deploys '{SCENE_FLOW_NAME}/NAME'; got --scene-deployment {scene_deployment!r}")
            dep_id = deploy_local(scene_pool, name=name, entrypoint=SCENE_ENTRYPOINT)
            console.print(f"deployment {scene_dep} ({dep_id}) on work pool {scene_pool}: scenes run there")
            scene_deployment = scene_dep
        sub = submit_collection(collection, store, cfg, deployment=deployment, per_image=per_image, tags=tag or [],
                                scene_deployment=scene_deployment)
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
