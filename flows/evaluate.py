"""The ``evaluate-store`` flow: the evaluation suite over every finished scene of a store.

One task per scene (``tasks/score.py``: the paper's Table I image metrics, III COLMAP camera pose errors,
IV 3DGS, V planning geometry and runtime), then Table II, FID / FVD over all scenes, then the rows go to the
``evaluations`` table and to ``evaluations/<evaluation_id>/report.{md,json}`` in the store, and to Prefect
artifacts (a table and the Markdown report). A scene that fails to score gets one failed Table I row
(``scoring``). Scores are kept per scene, so evaluating again with the same settings only
re-reads them.
"""

from __future__ import annotations

import json
import uuid
from dataclasses import dataclass, field
from pathlib import PurePath
from typing import Any

from prefect import flow, task
from prefect.artifacts import create_markdown_artifact, create_table_artifact
from prefect.task_runners import ThreadPoolTaskRunner

from navcrafter.flows.tools.report import read_manifest
from navcrafter.models.threads import one_blas_thread
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import EVALUATE
from navcrafter.schemas.tables import to_table, utcnow
from navcrafter.tasks import score
from navcrafter.tasks.clips import dataset as clip_tasks
from navcrafter.tasks.clips import reconstruction as clip_reconstruction
from navcrafter.tasks.common import open_store
from navcrafter.tasks.readers import scene_run_label


@dataclass
class EvaluationRun:
    evaluation_id: str
    rows: list[dict[str, Any]] = field(default_factory=list)
    report: str = ""  # store-relative path of the Markdown report
    failed: dict[str, str] = field(default_factory=dict)  # scene id -> error


def evaluable_scenes(store_uri: str) -> tuple[list[str], dict[str, str]]:
    """Scenes whose exploration finished (their ``evaluation`` group is complete), and a display name
    (the source file's name) for each."""
    store = open_store(store_uri)
    sources: dict[str, set[str]] = {}
    for r in read_manifest(store).to_pylist():
        if r.get("scene_id"):
            sources.setdefault(r["scene_id"], set()).add(PurePath(str(r["source"])).name)
    names = {sid: ", ".join(sorted(v)) for sid, v in sources.items()}
    ids = [sid for sid in store.scene_ids() if store.scene(sid).status(EVALUATE).complete]
    return ids, names


score_task = task(score.score_scene, name="score", task_run_name="score-{scene_id:.12}",
                  retries=1, retry_delay_seconds=2)
distribution_task = task(score.distribution_rows, name="fid-fvd")
score_clip_task = task(clip_tasks.score_clip, name="score-clip", task_run_name="score-clip-{key}")
clip_distribution_task = task(clip_tasks.clip_distribution_rows, name="fid-fvd")
reconstruction_task = task(clip_reconstruction.reconstruction_rows, name="reconstruct-clip",
                           task_run_name="reconstruct-clip-{key}")


@flow(name="evaluate-store", persist_result=False)
def evaluate_store(store: str, config: RunConfig, scene_ids: list[str] | None = None) -> EvaluationRun:
    """Score finished scenes of ``store`` (all of them unless ``scene_ids``) and write the tables."""
    with one_blas_thread():  # scenes run in threads: numpy's OpenBLAS pool hung when two entered it
        return _evaluate_store(store, config, scene_ids)


def _evaluate_store(store: str, config: RunConfig, scene_ids: list[str] | None = None) -> EvaluationRun:
    """The body of ``evaluate_store``."""
    evaluation_id = f"{utcnow():%Y%m%dT%H%M%S}-{uuid.uuid4().hex[:8]}"
    ids, names = evaluable_scenes(store)
    if scene_ids is not None:
        unknown = sorted(set(scene_ids) - set(ids))
        if unknown:
            raise ValueError(f"scene(s) {', '.join(s[:12] for s in unknown)} of {store} have not finished "
                             "exploring; run `navcrafter explore` first")
        ids = [s for s in ids if s in set(scene_ids)]
    result = EvaluationRun(evaluation_id)
    futures = {sid: score_task.submit(store, sid, config, evaluation_id) for sid in ids}
    scored = []
    for sid, fut in futures.items():
        try:
            result.rows += fut.result()
            scored.append(sid)
        except Exception as exc:  # one scene's failure is recorded; the others are still reported
            result.failed[sid] = f"{type(exc).__name__}: {exc}"
            result.rows.append(score.row("I", "scoring", status="failed", note=result.failed[sid], scene_id=sid))
    if scored:
        result.rows += distribution_task(store, scored, config)
    s = open_store(store)
    now = utcnow()
    s.tables.write("evaluations", [{**r, "evaluation_id": evaluation_id, "backend": config.backend,
                                    "created_at": now} for r in result.rows], part=evaluation_id)
    labels = [scene_run_label(s.scene(sid), config) for sid in ids]  # a scanned world's label names the scan
    md = score.evaluation_markdown(evaluation_id, result.rows, names, config.backend, labels)
    result.report = f"evaluations/{evaluation_id}/report.md"
    s.write_bytes(result.report, md.encode())
    s.write_bytes(f"evaluations/{evaluation_id}/report.json", json.dumps(
        {"evaluation_id": evaluation_id, "backend": config.backend, "scenes": ids, "names": names,
         "failed": result.failed, "rows": result.rows}, indent=1).encode())
    create_markdown_artifact(key="evaluation-report", markdown=md,
                             description=f"navcrafter evaluation {evaluation_id} ({config.backend})")
    create_table_artifact(key="evaluation-table", table=[
        {k: r[k] for k in ("scene_id", "table", "metric", "value", "unit", "status")} for r in result.rows],
        description=f"navcrafter evaluation {evaluation_id}: one row per scene and metric")
    return result


def evaluate_store_local(store: str, config: RunConfig) -> EvaluationRun:
    """The same flow on a thread pool sized by ``max_parallel_scenes``."""
    return evaluate_store.with_options(task_runner=ThreadPoolTaskRunner(
        max_workers=config.max_parallel_scenes))(store, config)


@flow(name="evaluate-clips", persist_result=False)
def evaluate_clips(clips: str, generated: str, out: str, config: RunConfig, reconstruction: bool = True
                   ) -> EvaluationRun:
    """Score the frames a generator made for dataset clips (``tasks/clips/dataset.py``: Tables I-III; with
    ``reconstruction``, Table IV: a 3DGS fit per clip, ``tasks/clips/reconstruction.py``, with ``config.fit``);
    writes ``out/evaluations.parquet`` (the evaluations schema) and ``out/report.{md,json}``."""
    from pathlib import Path

    import pyarrow.parquet as pq


    evaluation_id = f"{utcnow():%Y%m%dT%H%M%S}-{uuid.uuid4().hex[:8]}"
    keys = clip_tasks.clip_keys(clips)
    result = EvaluationRun(evaluation_id)
    futures = [score_clip_task.submit(Path(clips), Path(generated), key, config.evaluation) for key in keys]
    for key, fut in zip(keys, futures):
        rows = fut.result()
        result.rows += rows
        failed = [r["note"] for r in rows if r["status"] == "failed" and r["table"] == "I"]
        if failed:
            result.failed[key] = failed[0]
    scored = [k for k in keys if k not in result.failed]
    result.rows += clip_distribution_task(Path(clips), Path(generated), scored, config.evaluation)
    if reconstruction:
        fits = [reconstruction_task.submit(clips, generated, key, config) for key in scored]
        for fut in fits:
            result.rows += fut.result()
    backend = clip_tasks.generator_backend(Path(generated), scored)
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    now = utcnow()
    pq.write_table(to_table("evaluations", [{**r, "evaluation_id": evaluation_id, "backend": backend,
                                             "created_at": now} for r in result.rows]),
                   out_dir / "evaluations.parquet")
    md = score.evaluation_markdown(evaluation_id, result.rows, {}, backend)
    (out_dir / "report.md").write_text(md)
    (out_dir / "report.json").write_text(json.dumps({"evaluation_id": evaluation_id, "clips": keys,
                                                     "failed": result.failed, "rows": result.rows}, indent=1))
    result.report = str(out_dir / "report.md")
    create_markdown_artifact(key="clip-evaluation-report", markdown=md,
                             description=f"navcrafter clip evaluation {evaluation_id}")
    return result
