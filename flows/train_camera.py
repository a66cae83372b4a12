"""Prefect flow ``train-camera``: camera-control training as resumable tasks over a run folder.

``train_camera(run_dir, config, nproc)``: record the config (``prepare_run``) -> draw clips from the datasets
(``plan``) -> precompute their latents, CLIP features, text embeddings, render conditioning and cameras into the
clip store (``precompute``; complete clips are skipped, so a rerun resumes) -> train (``train``: in this process,
or ``nproc`` DDP processes through torchrun; resumes from the newest checkpoint) -> validate (the
camera-conditioning gap on held-out clips) -> export (``RUN/control``). Artifacts: a progress bar artifact
(``train-progress-<run>``) during training, and a Markdown artifact (``train-<run>``) with the loss curve and the
validation figures. Each task is a plain function of ``tasks/training``; the flow only orders them.
"""

from __future__ import annotations

import base64
import hashlib
import time
from pathlib import Path

from prefect import flow, task
from prefect.artifacts import create_markdown_artifact, create_progress_artifact, update_progress_artifact

from navcrafter.models.synthesis.training import STATE_FILE, latest_checkpoint
from navcrafter.schemas.training import CLIP_STORE, CameraTrainingConfig
from navcrafter.tasks.common import logger
from navcrafter.tasks.training import train as training
from navcrafter.tasks.training.clips import init_clip_store, plan_clips, precompute_clip


def _key(run_dir: str) -> str:
    return hashlib.sha1(str(Path(run_dir).resolve()).encode()).hexdigest()[:10]


@task(name="plan-clips", persist_result=False)
def plan_task(config: CameraTrainingConfig):

    refs = plan_clips(config)
    logger().info("drew %d clips (%d for validation)", len(refs),
                  sum(1 for r in refs if getattr(r, "split", "") == "validation"))
    return refs


@task(name="precompute-clips", persist_result=False)
def precompute_task(run_dir: str, refs) -> int:
    """Write every clip's group of the clip store (complete ones are skipped; the root holds the null prompt's
    embeddings)."""

    config = training.load_run_config(run_dir)
    encoders = training.build_encoders(config)
    store = Path(run_dir) / CLIP_STORE
    init_clip_store(store, encoders, config)
    for i, ref in enumerate(refs):
        precompute_clip(store, ref, encoders, config)
        if (i + 1) % 50 == 0 or i + 1 == len(refs):
            logger().info("precomputed %d/%d clips", i + 1, len(refs))
    return len(refs)


class _Progress:
    """Terminal progress bar + Prefect progress artifact + a log line every ``log_every`` steps."""

    def __init__(self, run_dir: str, start: int, total: int, log_every: int) -> None:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self.total, self.log_every, self.last = total, log_every, time.monotonic()
        self.bar = Progress(TextColumn("train-camera"), BarColumn(), MofNCompleteColumn(),
                            TextColumn("loss {task.fields[loss]}  {task.fields[rate]} clips/s"), TimeRemainingColumn())
        self.bar.start()
        self.task = self.bar.add_task("train", total=total, completed=start, loss="-", rate="-")
        try:
            self.artifact = create_progress_artifact(100.0 * start / total, key=f"train-progress-{_key(run_dir)}",
                                                     description=f"camera-control training of {run_dir}")
        except Exception:  # no Prefect context (direct calls): the terminal bar is enough
            self.artifact = None

    def __call__(self, log) -> None:
        self.bar.update(self.task, completed=log.step, loss=f"{log.loss:.4f}", rate=f"{log.clips_per_s:.2f}")
        if log.step % self.log_every == 0 or log.step == self.total:
            logger().info("step %d/%d loss %.5f lr %.2e %.2f clips/s", log.step, self.total, log.loss, log.lr,
                          log.clips_per_s)
        if self.artifact is not None and (time.monotonic() - self.last > 2.0 or log.step == self.total):
            try:
                update_progress_artifact(self.artifact, 100.0 * log.step / self.total)
                self.last = time.monotonic()
            except Exception as exc:
                logger().warning("progress artifact not updated: %s", exc)

    def close(self) -> None:
        self.bar.stop()


@task(name="train", persist_result=False)
def train_task(run_dir: str, nproc: int = 1) -> dict:
    config = training.load_run_config(run_dir)
    if nproc > 1:
        training.launch(run_dir, nproc)
        return {"steps": config.steps, "processes": nproc}

    ck = latest_checkpoint(run_dir)
    start = int(ck.name.split("-")[1]) if ck is not None else 0
    progress = _Progress(run_dir, start, config.steps, config.log_every)
    try:
        return training.train(run_dir, on_step=progress)
    finally:
        progress.close()


@task(name="validate", persist_result=False)
def validate_task(run_dir: str) -> dict:
    import json


    result = training.validate(run_dir)
    state = json.loads((latest_checkpoint(run_dir) / STATE_FILE).read_text())
    png = base64.b64encode(training.loss_curve_png(state["history"])).decode()
    frames = base64.b64encode(training.sample_frames_png(run_dir)).decode()
    history = [f"| {v['step']} | {v['loss_true_cameras']:.5f} | {v['loss_shuffled_cameras']:.5f} | "
               f"{v['camera_gap']:+.5f} |" for v in state.get("validation", [])]
    md = "\n".join([
        f"# Camera-control training: {run_dir}",
        f"![loss](data:image/png;base64,{png})", "",
        "Validation clip: stored (top) and sampled with its cameras by the newest checkpoint (bottom):", "",
        f"![frames](data:image/png;base64,{frames})",
        "", "| checkpoint | split | clips | loss, true cameras | loss, shuffled cameras | camera gap |",
        "|---|---|---|---|---|---|",
        f"| {result['checkpoint']} | {result['split']} | {result['clips']} | {result['loss_true_cameras']:.5f} | "
        f"{result['loss_shuffled_cameras']:.5f} | {result['camera_gap']:+.5f} |",
        *(["", "| step | loss, true cameras | loss, shuffled cameras | camera gap |", "|---|---|---|---|", *history]
          if history else []),
        "", "The camera-conditioning gap is the flow loss with another clip's cameras minus the loss with the "
        "clip's own: zero for a model that ignores the camera.",
    ])
    try:
        create_markdown_artifact(key=f"train-{_key(run_dir)}", markdown=md,
                                 description=f"camera-control training of {run_dir}")
    except Exception as exc:
        logger().warning("no training artifact: %s", exc)
    return result


@task(name="export-control", persist_result=False)
def export_task(run_dir: str) -> str:
    return str(training.export_control(run_dir))


@flow(name="train-camera", persist_result=False)
def train_camera(run_dir: str, config: CameraTrainingConfig, nproc: int = 1) -> dict:
    """Train the camera control of ``config`` into ``run_dir`` (resumes a run started there)."""
    training.prepare_run(run_dir, config)
    refs = plan_task(config)
    precompute_task(run_dir, refs)
    summary = train_task(run_dir, nproc)
    validation = validate_task(run_dir)
    control = export_task(run_dir)
    return {"training": summary, "validation": validation, "control": control}
