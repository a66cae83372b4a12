"""The ``generate-clips`` flow: the configured synthesizer on every clip of a folder of dataset clips, one task
per clip (``tasks/clips/generation.py``); scoring them is the ``evaluate-clips`` flow (``flows/evaluate.py``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from prefect import flow, task
from prefect.task_runners import ThreadPoolTaskRunner

from navcrafter.schemas.config import RunConfig
from navcrafter.tasks.clips import clip_keys
from navcrafter.tasks.clips import generation as clip_generation


@dataclass
class GenerationRun:
    generated: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)  # already made with the same settings
    failed: dict[str, str] = field(default_factory=dict)  # clip -> error
    records: dict[str, dict[str, Any]] = field(default_factory=dict)


generate_task = task(clip_generation.generate_clip, name="generate-clip", task_run_name="generate-clip-{key}")


@flow(name="generate-clips", persist_result=False)
def generate_clips(clips: str, generated: str, config: RunConfig) -> GenerationRun:
    """Frames for every clip of ``clips`` into ``generated/<clip>/``; one clip's failure does not stop the others."""
    keys = clip_keys(clips)
    Path(generated).mkdir(parents=True, exist_ok=True)
    run = GenerationRun()
    futures = {key: generate_task.submit(clips, generated, key, config) for key in keys}
    for key, fut in futures.items():
        try:
            rec = fut.result()
        except Exception as exc:  # recorded; the other clips go on
            run.failed[key] = f"{type(exc).__name__}: {exc}"
            continue
        run.records[key] = rec
        (run.skipped if rec.get("skipped") else run.generated).append(key)
    return run


def generate_clips_local(clips: str, generated: str, config: RunConfig) -> GenerationRun:
    """The same flow on a thread pool sized by ``max_parallel_scenes``."""
    return generate_clips.with_options(task_runner=ThreadPoolTaskRunner(
        max_workers=config.max_parallel_scenes))(clips, generated, config)
