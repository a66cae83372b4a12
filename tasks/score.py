"""The evaluation suite on a finished scene: the rows of the paper-shaped tables (``navcrafter evaluate``).

Tables (the ``table`` column of the ``evaluations`` Arrow table, ``schemas/tables.py``):

* **III, synthesis quality**: PSNR / SSIM / LPIPS of the synthesized frames against reference frames
  (per scene), FID / FVD over all scenes (``flows/evaluate.py``). A single photo has no reference
  frames: only simulation scenes have them (the true renders at the requested cameras; the simulated
  synthesizer *is* that renderer, so these rows only check that stored frames match their cameras).
* **IV, camera-guidance precision**: COLMAP poses of ``evaluation.pose_frames`` frames of every clip
  against the requested trajectory (``models/metrics/pose.py``): R_err, T_err, registered frames.
* **V, runtime**: seconds per stage, from the steps' recorded execution times.
* **VI, exploration geometry**: Coverage, Noise ratio, F-score at 2 cm and collisions (``tasks/evaluate``).
* **VII, 3DGS rendering**: held-out PSNR / SSIM / LPIPS of the fit step (``unavailable`` when it did not run).

A metric that cannot be computed here has ``status`` ``unavailable`` (weights missing, no reference)
or ``not_built`` and a ``note`` saying why; it is never filled with a made-up value.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable
from typing import Any

import numpy as np

from navcrafter.models.metrics.evalnets.weights import MetricUnavailable
from navcrafter.schemas.config import EvaluationConfig, RunConfig
from navcrafter.schemas.layout import EVALUATE, FIT, LIFT, PLAN, REFINE, SYNTHESIZE
from navcrafter.schemas.store import SceneStore
from navcrafter.tasks import steps
from navcrafter.tasks.common import open_store, simulation_truth
from navcrafter.tasks.readers import camera_path
from navcrafter.tasks.steps import StepContext

TABLES = {
    "III": "Synthesis quality",
    "IV": "Camera-guidance precision",
    "V": "Runtime",
    "VI": "Exploration geometry",
    "VII": "3DGS rendering quality",
}
SIM_REFERENCE_NOTE = ("simulation: reference = true renders at the requested cameras, which the simulated "
                      "synthesizer also produces; checks frame/camera alignment, not a video model")


def row(table: str, metric: str, value: float | None = None, unit: str | None = None, *,
        status: str = "ok", note: str | None = None, scene_id: str | None = None) -> dict[str, Any]:
    """One row of the evaluations table (without the run-level columns)."""
    if status == "ok" and (value is None or (isinstance(value, float) and math.isnan(value))):
        status, note = "failed", note or "no value"
    return {"scene_id": scene_id, "table": table, "metric": metric,
            "value": None if status != "ok" else float(value), "unit": unit, "status": status, "note": note}


def clip_indices(num_frames: int, count: int) -> np.ndarray:
    """``count`` frame indices evenly spaced over a clip, first and last included."""
    return np.unique(np.round(np.linspace(0, num_frames - 1, min(count, num_frames))).astype(int))


def scene_iterations(scene: SceneStore) -> int:
    attrs = scene.require_complete(EVALUATE).attrs
    if "iterations" not in attrs:
        raise ValueError(f"scene {scene.scene_id[:12]} was evaluated by an older navcrafter; run the same "
                         "`navcrafter explore` again (it only refreshes the evaluation), then evaluate")
    return int(attrs["iterations"])


# -- table III --------------------------------------------------------------------------------------
def reference_frames(scene: SceneStore, k: int, idx: np.ndarray) -> np.ndarray | None:
    """Ground-truth frames at the requested cameras ``idx`` of iteration ``k`` (simulation only)."""
    truth = simulation_truth(scene)
    if truth is None:
        return None
    from navcrafter.models.simulation.render import render

    frames = scene.read(SYNTHESIZE, k, "frames")
    H, W = frames.shape[1:3]
    K = truth.intrinsics_for(H, W)
    poses = truth.gt_pose(scene.read(PLAN, k, "trajectory")[idx])
    return np.stack([render(truth.scene, c2w, K).rgb for c2w in poses])


def synthesis_rows(scene: SceneStore, config: RunConfig, iterations: int) -> list[dict[str, Any]]:
    fake, real = [], []
    for k in range(1, iterations + 1):
        idx = clip_indices(len(scene.read(PLAN, k, "trajectory")), config.evaluation.pose_frames)
        ref = reference_frames(scene, k, idx)
        if ref is None:
            note = "no reference frames for a single photo (score dataset clips for these metrics)"
            return [row("III", m, status="unavailable", note=note) for m in ("PSNR", "SSIM", "LPIPS")]
        fake.append(scene.read(SYNTHESIZE, k, "frames")[idx])
        real.append(ref)
    if not fake:
        return [row("III", m, status="unavailable", note="no iterations") for m in ("PSNR", "SSIM", "LPIPS")]
    return image_quality_rows(np.concatenate(fake), np.concatenate(real), config.evaluation, SIM_REFERENCE_NOTE)


def image_quality_rows(fake: np.ndarray, real: np.ndarray, config: EvaluationConfig, note: str | None = None,
                       scene_id: str | None = None) -> list[dict[str, Any]]:
    """PSNR, SSIM and LPIPS (mean over frames) of uint8 frames ``fake`` against ``real`` (``N x H x W x 3``)."""
    from navcrafter.models.metrics.image import psnr, ssim

    a, b = fake.astype(np.float64) / 255.0, real.astype(np.float64) / 255.0
    p = np.asarray(psnr(a, b), dtype=np.float64)
    capped = "identical frames give inf, capped at 100 dB" if np.isinf(p).any() else None
    rows = [row("III", "PSNR", float(np.mean(np.minimum(p, 100.0))), "dB",
                note="; ".join(x for x in (note, capped) if x) or None, scene_id=scene_id),
            row("III", "SSIM", float(np.mean(ssim(a, b))), None, note=note, scene_id=scene_id)]
    try:
        from navcrafter.models.metrics.evalnets.lpips import lpips_distance

        d = lpips_distance(a.astype(np.float32), b.astype(np.float32), net=config.lpips_net,
                           weights_dir=config.weights_dir)
        rows.append(row("III", "LPIPS", float(np.mean(d)), None, scene_id=scene_id,
                        note="; ".join(x for x in (config.lpips_net, note) if x)))
    except MetricUnavailable as exc:
        rows.append(row("III", "LPIPS", status="unavailable", note=str(exc), scene_id=scene_id))
    return rows


# -- table IV ---------------------------------------------------------------------------------------
def camera_rows(scene: SceneStore, config: RunConfig, iterations: int) -> list[dict[str, Any]]:
    metrics = ("R_err", "T_err", "registered")
    if not config.evaluation.camera_guidance:
        return [row("IV", m, status="unavailable", note="evaluation.camera_guidance is off") for m in metrics]
    if iterations == 0:
        return [row("IV", m, status="unavailable", note="no iterations") for m in metrics]
    from navcrafter.models.metrics.pose import camera_guidance_precision

    r_err, t_err, registered, total, notes = [], [], 0, 0, []
    path = camera_path(scene, config, iterations)
    for k in range(1, iterations + 1):
        clip = path.clip(k)
        idx = clip_indices(len(clip), config.evaluation.pose_frames)
        frames = scene.read(SYNTHESIZE, k, "frames")[idx]
        with tempfile.TemporaryDirectory(prefix="navcrafter-colmap-") as work:
            res = camera_guidance_precision(frames, clip.c2w[idx], clip.K[0], work, scale="farthest", num_threads=2)
        registered += int(res["n_registered"])
        total += int(res["n_frames"])
        if np.isfinite(res["R_err_deg_sum"]) and np.isfinite(res["T_err_sum"]):
            r_err.append(float(res["R_err_deg_sum"]))
            t_err.append(float(res["T_err_sum"]))
        if res.get("reason"):
            notes.append(f"iteration {k}: {res['reason']}")
    note = (f"COLMAP (known K) on {len(idx)} frames per clip, {iterations} clips; relative to the first frame, "
            "trajectories scaled to unit extent; per clip sums over frames, mean over clips"
            + (f"; {'; '.join(notes)}" if notes else ""))
    rows = [row("IV", "registered", registered / max(total, 1), "fraction",
                note=f"{registered} of {total} frames registered by COLMAP")]
    if r_err:
        rows += [row("IV", "R_err", float(np.mean(r_err)), "deg, sum per clip", note=note),
                 row("IV", "T_err", float(np.mean(t_err)), "unit extent, sum per clip", note=note)]
    else:
        rows += [row("IV", m, status="failed", note="COLMAP registered no clip: " + note) for m in ("R_err", "T_err")]
    return rows


# -- tables V, VI, VII -----------------------------------------------------------------------------
def runtime_rows(scene: SceneStore, iterations: int) -> list[dict[str, Any]]:
    from navcrafter.schemas.layout import EXPORT, GEOMETRY

    def secs(step, k=None) -> float:
        st = scene.status(step, k)
        return float(st.attrs.get("seconds", 0.0)) if st.complete else 0.0

    stages = {"geometry": secs(GEOMETRY),
              "plan": sum(secs(PLAN, k) for k in range(1, iterations + 1)),
              "synthesize": sum(secs(SYNTHESIZE, k) for k in range(1, iterations + 1)),
              "lift": sum(secs(LIFT, k) for k in range(1, iterations + 1)),
              "export": secs(EXPORT), "evaluate": secs(EVALUATE)}
    rows = [row("V", name, value, "s") for name, value in stages.items()]
    rows.append(row("V", "total", sum(stages.values()), "s", note="step execution time, no orchestration"))
    return rows


GEOMETRY_METRICS = (("coverage", "Coverage", "fraction"), ("noise_ratio", "Noise ratio", "fraction"),
                    ("fscore", "F-score", "fraction"), ("collisions", "Collisions", "count"))


def geometry_rows(scene: SceneStore, config: RunConfig) -> list[dict[str, Any]]:
    metrics = scene.require_complete(EVALUATE).attrs.get("metrics", {})
    rows = []
    for key, name, unit in GEOMETRY_METRICS:
        if key in metrics:
            rows.append(row("VI", name, float(metrics[key]), unit, note="2 cm threshold, vs. true surfaces"))
        else:
            rows.append(row("VI", name, status="unavailable", note="needs ground-truth surfaces (simulation scenes)"))
    return rows


def gaussian_rows(scene: SceneStore) -> list[dict[str, Any]]:
    """Held-out rendering quality of the fitted 3DGS scene (the fit step's attrs), when the fit ran."""
    status = scene.status(FIT)
    if not status.complete:
        note = "the 3DGS fit did not run for this scene (fit.enabled is false)"
        return [row("VII", m, status="unavailable", note=note) for m in ("PSNR", "SSIM", "LPIPS")]
    a = status.attrs
    note = f"{a['n_holdout']} held-out frames (every {a['holdout_every']}th), {a['resolution'][0]}x{a['resolution'][1]}"
    rows = [row("VII", "PSNR", float(a["psnr"]), "dB", note=note),
            row("VII", "SSIM", float(a["ssim"]), None, note=note)]
    if a.get("lpips") is None:
        rows.append(row("VII", "LPIPS", status="unavailable", note=a.get("lpips_note", "")))
    else:
        rows.append(row("VII", "LPIPS", float(a["lpips"]), None, note=f"{note}; {a.get('lpips_note', '')}"))
    refined = scene.status(REFINE)
    if refined.complete:  # the same held-out frames, after the refine step trained with refined views
        r = refined.attrs
        rnote = f"{note}; after the refine step ({r['n_views']} refined views, refiner: {r['refiner']})"
        rows += [row("VII", "PSNR (refined)", float(r["psnr"]), "dB", note=rnote),
                 row("VII", "SSIM (refined)", float(r["ssim"]), None, note=rnote)]
        if r.get("lpips") is not None:
            rows.append(row("VII", "LPIPS (refined)", float(r["lpips"]), None, note=rnote))
    return rows


def scene_rows(scene: SceneStore, config: RunConfig) -> list[dict[str, Any]]:
    """All per-scene rows of the evaluation suite."""
    iterations = scene_iterations(scene)
    rows = (synthesis_rows(scene, config, iterations) + camera_rows(scene, config, iterations)
            + runtime_rows(scene, iterations) + geometry_rows(scene, config) + gaussian_rows(scene))
    for r in rows:
        r["scene_id"] = scene.scene_id
    return rows


def score(ctx: StepContext) -> dict[str, Any]:
    """The score step: one scene's rows of the evaluation suite."""
    return {"rows": scene_rows(ctx.scene, ctx.config)}


def score_scene(store_uri: str, scene_id: str, config: RunConfig, run_id: str) -> list[dict[str, Any]]:
    """Run (or read back) the score step of an explored scene: its rows."""
    return [dict(r) for r in steps.run_attrs(store_uri, scene_id, "score", config, run_id)["rows"]]


# -- over all scenes: FID / FVD --------------------------------------------------------------------
def distribution_rows(store_uri: str, scene_ids: list[str], config: RunConfig) -> list[dict[str, Any]]:
    """FID (frames) and FVD (clips) of the synthesized clips against the reference clips of all scenes.

    Needs reference clips (simulation scenes) and the official Inception / I3D weights; otherwise the
    rows say which is missing. Frames are read scene by scene, at ``evaluation.pose_frames`` per clip.
    """
    store = open_store(store_uri)

    def clips() -> tuple[list[np.ndarray], list[np.ndarray]]:
        real, fake = [], []
        for sid in scene_ids:
            scene = store.scene(sid)
            for k in range(1, scene_iterations(scene) + 1):
                idx = clip_indices(len(scene.read(PLAN, k, "trajectory")), config.evaluation.pose_frames)
                ref = reference_frames(scene, k, idx)
                if ref is not None:
                    real.append(ref)
                    fake.append(scene.read(SYNTHESIZE, k, "frames")[idx])
        return real, fake

    return frechet_rows(clips, config.evaluation, SIM_REFERENCE_NOTE)


def frechet_rows(clips: Callable[[], tuple[list[np.ndarray], list[np.ndarray]]], config: EvaluationConfig,
                 note: str | None = None) -> list[dict[str, Any]]:
    """FID over all frames and FVD over all clips; ``clips()`` gives (real, fake) lists of uint8
    ``T x H x W x 3`` clips and is only called when a metric's weights are there."""
    from navcrafter.models.metrics.evalnets import fidfvd

    rows: list[dict[str, Any]] = []
    loaded: tuple[list[np.ndarray], list[np.ndarray]] | None = None
    for metric in ("FID", "FVD"):
        try:
            fidfvd.require_weights(metric, config.weights_dir)
        except MetricUnavailable as exc:
            rows.append(row("III", metric, status="unavailable", note=str(exc)))
            continue
        loaded = loaded or clips()
        real = [c.astype(np.float32) / 255.0 for c in loaded[0]]
        fake = [c.astype(np.float32) / 255.0 for c in loaded[1]]
        if len(fake) < 2:
            rows.append(row("III", metric, status="unavailable", note=f"needs at least 2 clips (have {len(fake)})"))
            continue
        # "gram" is the exact Frechet distance through the samples' Gram matrix: milliseconds for few
        # samples, where sqrtm of the 2048x2048 covariance product takes ~25 s on 2 cores.
        if metric == "FID":
            a, b = np.concatenate(real), np.concatenate(fake)
            value = fidfvd.fid(a, b, config.weights_dir, method="gram" if len(a) < 2048 else "sqrtm")
        else:
            value = fidfvd.fvd(np.stack(real), np.stack(fake), config.weights_dir,
                               method="gram" if len(real) < 400 else "sqrtm")
        rows.append(row("III", metric, value, None, note="; ".join(x for x in (f"{len(fake)} clips", note) if x)))
    return rows


# -- the report ------------------------------------------------------------------------------------
def _cell(r: dict[str, Any], notes: list[str]) -> str:
    if r["status"] == "ok":
        v = r["value"]
        return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.0f}"
    text = f"{r['status']}: {r['note']}" if r.get("note") else r["status"]
    if text not in notes:
        notes.append(text)
    return f"{r['status']} [{notes.index(text) + 1}]"


def evaluation_markdown(evaluation_id: str, rows: list[dict[str, Any]], names: dict[str, str],
                        backend: str) -> str:
    """The paper-shaped tables (one per ``TABLES`` entry: scenes as rows, metrics as columns)."""
    from navcrafter.models.simulation import LABEL as SIM_LABEL

    lines = ["# navcrafter evaluation", ""]
    if backend == "simulation":
        lines += [f"> **{SIM_LABEL}.** Scores measure the pipeline on generated scenes, not learned models.", ""]
    lines += [f"Evaluation {evaluation_id}: {len({r['scene_id'] for r in rows if r['scene_id']})} scenes, "
              f"backend '{backend}'.", ""]
    notes: list[str] = []
    for table, title in TABLES.items():
        trows = [r for r in rows if r["table"] == table]
        if not trows:
            continue
        metrics = list(dict.fromkeys(r["metric"] for r in trows))
        units = {r["metric"]: r["unit"] for r in trows if r.get("unit")}
        header = [f"{m} ({units[m]})" if m in units else m for m in metrics]
        lines += [f"## Table {table}: {title}", "", "| scene | " + " | ".join(header) + " |",
                  "|---|" + "---:|" * len(metrics)]
        keys = list(dict.fromkeys(r["scene_id"] for r in trows))
        for sid in keys:
            by_metric = {r["metric"]: r for r in trows if r["scene_id"] == sid}
            label = "all scenes" if sid is None else f"{names.get(sid, '')} `{sid[:12]}`".strip()
            cells = [_cell(by_metric[m], notes) if m in by_metric else "" for m in metrics]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        lines.append("")
    if notes:
        lines += ["Notes:", ""] + [f"{i}. {n.replace('|', '/')}" for i, n in enumerate(notes, 1)] + [""]
    return "\n".join(lines)
