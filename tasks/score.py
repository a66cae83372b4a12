"""The evaluation suite on a finished scene: the rows of the paper-shaped tables (``navcrafter evaluate``).

Tables (the ``table`` column of the ``evaluations`` Arrow table, ``schemas/tables.py``), numbered as the paper's:

* **I, novel-view synthesis quality**: PSNR / SSIM / LPIPS of the synthesized frames against reference frames
  (per scene). A single photo has no reference frames: only simulation scenes have them (the true renders at
  the requested cameras; the simulated synthesizer *is* that renderer, so these rows only check that stored
  frames match their cameras).
* **II, FID / FVD**: over all scenes (``flows/evaluate.py``), on the same frames as table I.
* **III, camera pose errors**: COLMAP poses of every clip's scored frames against the requested trajectory
  (``models/metrics/pose.py``): R_err, T_err (per-frame means, the headline), their per-clip sums, and the
  fraction of frames COLMAP registered (the unregistered ones are listed in the note).
* **IV, 3D scene reconstruction (3DGS)**: PSNR / SSIM / LPIPS of the fit step on held-out *synthesized*
  frames (``unavailable`` when it did not run); not the paper's protocol, which renders at a dataset's own frames.
* **V, planning**: Coverage, Noise ratio, F-score at 2 cm and collisions (``tasks/scene_metrics.py``), then the
  runtime (minutes per scene, as the paper's 4.79 min) and the seconds of each stage (``time: <stage>``).
* Table VI (the 3DGS ablation) is a benchmark, ``benchmarks/fitting.py``, not a row of this suite.

Which frames are scored (``evaluation.frame_choice``, :func:`scored_frames`): ``"first"`` (default, the paper's
protocol) scores the ``pose_frames`` frames after the conditioning frame (frame 0, the conditioning image an
I2V model reproduces) with the image metrics, and gives COLMAP the conditioning frame too (frames
``0..pose_frames``, as the dataset-clip scoring does); ``"spaced"`` scores ``pose_frames`` frames evenly spaced
over the clip, first and last included, with both.

A metric that cannot be computed here has ``status`` ``unavailable`` (weights missing, no reference)
or ``not_built`` and a ``note`` saying why; it is never filled with a made-up value.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from navcrafter.models.metrics.evalnets import fidfvd
from navcrafter.models.metrics.evalnets.lpips import lpips_distance
from navcrafter.models.metrics.evalnets.weights import MetricUnavailable
from navcrafter.models.metrics.image import SSIM_WINDOW, psnr, ssim, ssim_map
from navcrafter.models.metrics.pose import camera_guidance_precision
from navcrafter.models.simulation import simulation_label
from navcrafter.models.simulation.render import render
from navcrafter.schemas.config import EvaluationConfig, RunConfig
from navcrafter.schemas.layout import EVALUATE, EXPORT, FIT, GEOMETRY, LIFT, PLAN, REFINE, STEPS, SYNTHESIZE
from navcrafter.schemas.store import SceneStore
from navcrafter.tasks import steps
from navcrafter.tasks.common import open_store, simulation_truth
from navcrafter.tasks.readers import camera_path
from navcrafter.tasks.steps import StepContext

TABLES = {
    "I": "Novel-view synthesis quality",
    "II": "FID / FVD",
    "III": "Camera pose errors",
    "IV": "3D scene reconstruction (3DGS)",
    "V": "Planning: coverage, noise, F-score, runtime",
}
ABLATION_LINE = ("Table VI (3DGS ablation) is not scored here: it is the benchmark `benchmarks/fitting.py` "
                 "(see benchmarks/README.md).")
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


def scored_frames(num_frames: int, config: EvaluationConfig) -> tuple[np.ndarray, np.ndarray]:
    """The frame indices of a clip of ``num_frames`` frames scored by the image metrics (tables I and II)
    and by COLMAP (table III), per ``config.frame_choice``.

    ``"first"``: frames ``1..pose_frames`` for the image metrics (frame 0 is the conditioning image itself,
    which would score a copy) and ``0..pose_frames`` for COLMAP (the conditioning frame + 14, as the paper
    and the dataset-clip scoring do; the errors are relative to frame 0), both cut at the clip's end.
    ``"spaced"``: ``pose_frames`` frames evenly spaced over the clip (:func:`clip_indices`) for both.
    """
    if config.frame_choice == "spaced":
        idx = clip_indices(num_frames, config.pose_frames)
        return idx, idx
    last = min(config.pose_frames, num_frames - 1)
    return np.arange(1, last + 1), np.arange(0, last + 1)


def frames_note(config: EvaluationConfig, count: int) -> str:
    if config.frame_choice == "spaced":
        return f"{count} frames per clip, evenly spaced"
    return f"frames 0-{count - 1} of each clip (the conditioning frame and the {count - 1} after it)"


def scene_iterations(scene: SceneStore) -> int:
    attrs = scene.require_complete(EVALUATE).attrs
    if "iterations" not in attrs:
        raise ValueError(f"scene {scene.scene_id[:12]} was evaluated by an older navcrafter; run the same "
                         "`navcrafter explore` again (it only refreshes the evaluation), then evaluate")
    return int(attrs["iterations"])


# -- table I ----------------------------------------------------------------------------------------
def reference_frames(scene: SceneStore, k: int, idx: np.ndarray) -> np.ndarray | None:
    """Ground-truth frames at the requested cameras ``idx`` of iteration ``k`` (simulation only)."""
    truth = simulation_truth(scene)
    if truth is None:
        return None

    frames = scene.read(SYNTHESIZE, k, "frames")
    H, W = frames.shape[1:3]
    K = truth.intrinsics_for(H, W)
    poses = truth.gt_pose(scene.read(PLAN, k, "trajectory")[idx])
    return np.stack([render(truth.scene, c2w, K).rgb for c2w in poses])


def reference_valid(scene: SceneStore, k: int, idx: np.ndarray) -> np.ndarray | None:
    """Where the reference frames of ``reference_frames`` show scanned surface ``[N, H, W]`` (a world from a real
    scan: its holes are *no data*, skipped by the scores); None for generated scenes (every pixel counts)."""
    truth = simulation_truth(scene)
    if truth is None or getattr(truth.scene, "kind", None) != "scan":
        return None
    H, W = scene.read(SYNTHESIZE, k, "frames").shape[1:3]
    K = truth.intrinsics_for(H, W)
    poses = truth.gt_pose(scene.read(PLAN, k, "trajectory")[idx])
    return np.stack([render(truth.scene, c2w, K, colour=False).hit for c2w in poses])


def synthesis_rows(scene: SceneStore, config: RunConfig, iterations: int) -> list[dict[str, Any]]:
    fake, real, valid = [], [], []
    for k in range(1, iterations + 1):
        idx = scored_frames(len(scene.read(PLAN, k, "trajectory")), config.evaluation)[0]
        ref = reference_frames(scene, k, idx)
        if ref is None:
            note = "no reference frames for a single photo (score dataset clips for these metrics)"
            return [row("I", m, status="unavailable", note=note) for m in ("PSNR", "SSIM", "LPIPS")]
        fake.append(scene.read(SYNTHESIZE, k, "frames")[idx])
        real.append(ref)
        valid.append(reference_valid(scene, k, idx))
    if not fake:
        return [row("I", m, status="unavailable", note="no iterations") for m in ("PSNR", "SSIM", "LPIPS")]
    mask = None if any(v is None for v in valid) else np.concatenate(valid)
    return image_quality_rows(np.concatenate(fake), np.concatenate(real), config.evaluation, SIM_REFERENCE_NOTE,
                              valid=mask)


def image_quality_rows(fake: np.ndarray, real: np.ndarray, config: EvaluationConfig, note: str | None = None,
                       scene_id: str | None = None, valid: np.ndarray | None = None) -> list[dict[str, Any]]:
    """PSNR, SSIM and LPIPS (mean over frames) of uint8 frames ``fake`` against ``real`` (``N x H x W x 3``).
    ``valid [N, H, W]``: the pixels to score (a scanned world's holes are no data): PSNR and SSIM over them only
    (LPIPS sees whole frames)."""

    a, b = fake.astype(np.float64) / 255.0, real.astype(np.float64) / 255.0
    if valid is not None and not valid.all():
        return _masked_quality_rows(a, b, valid, note, scene_id) + image_quality_rows(
            fake, real, config, note, scene_id)[2:]
    p = np.asarray(psnr(a, b), dtype=np.float64)
    capped = "identical frames give inf, capped at 100 dB" if np.isinf(p).any() else None
    rows = [row("I", "PSNR", float(np.mean(np.minimum(p, 100.0))), "dB",
                note="; ".join(x for x in (note, capped) if x) or None, scene_id=scene_id),
            row("I", "SSIM", float(np.mean(ssim(a, b))), None, note=note, scene_id=scene_id)]
    try:
        d = lpips_distance(a.astype(np.float32), b.astype(np.float32), net=config.lpips_net,
                           weights_dir=config.weights_dir)
        rows.append(row("I", "LPIPS", float(np.mean(d)), None, scene_id=scene_id,
                        note="; ".join(x for x in (config.lpips_net, note) if x)))
    except MetricUnavailable as exc:
        rows.append(row("I", "LPIPS", status="unavailable", note=str(exc), scene_id=scene_id))
    return rows


def _masked_quality_rows(a: np.ndarray, b: np.ndarray, valid: np.ndarray, note: str | None,
                         scene_id: str | None) -> list[dict[str, Any]]:
    """PSNR over the ``valid`` pixels of each frame, SSIM over its windows that are all valid (frames without any
    are left out)."""
    keep = valid.reshape(len(valid), -1).any(1)
    if not keep.any():
        return [row("I", m, status="unavailable", note="no scanned surface in any reference frame", scene_id=scene_id)
                for m in ("PSNR", "SSIM")]
    a, b, v = a[keep], b[keep], valid[keep]
    mse = np.array([((x - y) ** 2)[m].mean() for x, y, m in zip(a, b, v, strict=True)])
    with np.errstate(divide="ignore"):
        p = np.minimum(10.0 * np.log10(1.0 / mse), 100.0)
    smap = ssim_map(a, b).mean(-1)
    # an SSIM window counts only when all its pixels are scanned
    vm = np.lib.stride_tricks.sliding_window_view(v, (SSIM_WINDOW, SSIM_WINDOW), axis=(1, 2)).all(axis=(-2, -1))
    s = np.array([m_[w].mean() if w.any() else np.nan for m_, w in zip(smap, vm, strict=True)])
    masked = f"over scanned pixels only ({v.mean():.0%}; holes are no data)"
    full = "; ".join(x for x in (note, masked) if x)
    return [row("I", "PSNR", float(np.mean(p)), "dB", note=full, scene_id=scene_id),
            row("I", "SSIM", float(np.nanmean(s)), None, note=full, scene_id=scene_id)]


# -- table III --------------------------------------------------------------------------------------
POSE_METRICS = ("R_err", "T_err", "R_err sum", "T_err sum", "registered")
POSE_UNITS = {"R_err": "rad, per-frame mean", "T_err": "unit extent, per-frame mean",
              "R_err sum": "deg, per clip", "T_err sum": "unit extent, per clip"}
POSE_NOTE = ("per-frame means over the registered frames but the reference (R_err in radians, like CameraCtrl's "
             "arccos RotErr), and per-clip sums (R_err sum in degrees); relative to the first registered frame, "
             "both paths scaled to unit extent; mean over clips")


def pose_error_rows(clips: Sequence[tuple[str, dict[str, Any], np.ndarray]], note: str,
                    scene_id: str | None = None) -> list[dict[str, Any]]:
    """Table III rows from :func:`~navcrafter.models.metrics.pose.camera_guidance_precision` results.

    ``clips``: one ``(label, result, frames)`` per clip: a label for the notes (``"iteration 2"``, or ``""``
    for a lone clip), the result (``scale="farthest"``) and the clip-frame index of every frame COLMAP got.

    The headline ``R_err`` / ``T_err`` are **per-frame means** (``R_err_deg_mean`` / ``T_err_mean``: over the
    registered frames other than the reference), ``R_err`` in **radians**: CameraCtrl's RotErr, which the
    paper adopts, is an arccos, i.e. radians, and the paper's values (0.021-1.207) read as degrees per frame
    would lie far below what COLMAP itself resolves on perfect 256x256 frames (a few tenths of a degree per
    frame, models/metrics/README.md). ``T_err`` is in units of the trajectory's extent. The per-clip sums
    (CameraCtrl's form; ``R_err sum`` in degrees) follow as ``R_err sum`` / ``T_err sum``; every value is the
    mean over the clips COLMAP could compare. ``registered`` is the fraction of frames COLMAP registered; its
    note lists the unregistered frames (clip-frame indices), which no error includes.
    """
    r_mean, t_mean, r_sum, t_sum, reasons, lost = [], [], [], [], [], []
    registered = total = 0
    for label, res, frames in clips:
        registered += int(res["n_registered"])
        total += int(res["n_frames"])
        if np.isfinite(res["R_err_deg_mean"]) and np.isfinite(res["T_err_mean"]):
            r_mean.append(float(np.deg2rad(res["R_err_deg_mean"])))
            t_mean.append(float(res["T_err_mean"]))
            r_sum.append(float(res["R_err_deg_sum"]))
            t_sum.append(float(res["T_err_sum"]))
        prefix = f"{label}: " if label else ""
        if res.get("reason"):
            reasons.append(prefix + str(res["reason"]))
        flags = (res.get("recovery") or {}).get("registered")
        if flags is not None:
            missing = [int(f) for f, ok in zip(np.asarray(frames).tolist(), flags) if not ok]
            if missing:
                lost.append(prefix + ", ".join(map(str, missing)))
    note = "; ".join([note, POSE_NOTE] + reasons)
    reg_note = f"{registered} of {total} frames registered by COLMAP"
    reg_note += f"; unregistered frames: {'; '.join(lost)}" if lost else "; every frame registered"
    if not r_mean:
        rows = [row("III", m, unit=POSE_UNITS[m], status="failed", note="COLMAP registered no clip: " + note,
                    scene_id=scene_id) for m in POSE_METRICS[:4]]
    else:
        rows = [row("III", m, float(np.mean(v)), POSE_UNITS[m], note=note, scene_id=scene_id)
                for m, v in zip(POSE_METRICS, (r_mean, t_mean, r_sum, t_sum))]
    return rows + [row("III", "registered", registered / max(total, 1), "fraction", note=reg_note,
                       scene_id=scene_id)]


def camera_rows(scene: SceneStore, config: RunConfig, iterations: int) -> list[dict[str, Any]]:
    if not config.evaluation.camera_guidance:
        return [row("III", m, status="unavailable", note="evaluation.camera_guidance is off") for m in POSE_METRICS]
    if iterations == 0:
        return [row("III", m, status="unavailable", note="no iterations") for m in POSE_METRICS]

    results = []
    path = camera_path(scene, config, iterations)
    for k in range(1, iterations + 1):
        clip = path.clip(k)
        idx = scored_frames(len(clip), config.evaluation)[1]
        frames = scene.read(SYNTHESIZE, k, "frames")[idx]
        with tempfile.TemporaryDirectory(prefix="navcrafter-colmap-") as work:
            res = camera_guidance_precision(frames, clip.c2w[idx], clip.K[0], work, scale="farthest", num_threads=2)
        results.append((f"iteration {k}", res, idx))
    note = (f"COLMAP (known K) on {frames_note(config.evaluation, len(results[0][2]))}, {iterations} clips")
    return pose_error_rows(results, note)


# -- table IV ---------------------------------------------------------------------------------------
def gaussian_rows(scene: SceneStore) -> list[dict[str, Any]]:
    """Held-out rendering quality of the fitted 3DGS scene (the fit step's attrs), when the fit ran.

    Scored on held-out *synthesized* frames (every ``holdout_every``-th frame of our own video: mostly
    interpolation), not the paper's protocol (renders at a dataset's own frames: dataset clips)."""
    status = scene.status(FIT)
    if not status.complete:
        note = "the 3DGS fit did not run for this scene (fit.enabled is false)"
        return [row("IV", m, status="unavailable", note=note) for m in ("PSNR", "SSIM", "LPIPS")]
    a = status.attrs
    note = (f"{a['n_holdout']} held-out synthesized frames (every {a['holdout_every']}th of our own video, "
            f"i.e. interpolation), {a['resolution'][0]}x{a['resolution'][1]}; not the paper's protocol "
            "(renders at a dataset's own frames: `navcrafter generate-clips` + `evaluate-clips`)")
    rows = [row("IV", "PSNR", float(a["psnr"]), "dB", note=note),
            row("IV", "SSIM", float(a["ssim"]), None, note=note)]
    if a.get("lpips") is None:
        rows.append(row("IV", "LPIPS", status="unavailable", note=a.get("lpips_note", "")))
    else:
        rows.append(row("IV", "LPIPS", float(a["lpips"]), None, note=f"{note}; {a.get('lpips_note', '')}"))
    refined = scene.status(REFINE)
    if refined.complete:  # the same held-out frames, after the refine step trained with refined views
        r = refined.attrs
        rnote = f"{note}; after the refine step ({r['n_views']} refined views, refiner: {r['refiner']})"
        rows += [row("IV", "PSNR (refined)", float(r["psnr"]), "dB", note=rnote),
                 row("IV", "SSIM (refined)", float(r["ssim"]), None, note=rnote)]
        if r.get("lpips") is not None:
            rows.append(row("IV", "LPIPS (refined)", float(r["lpips"]), None, note=rnote))
    return rows


# -- table V ----------------------------------------------------------------------------------------
GEOMETRY_METRICS = (("coverage", "Coverage", "fraction"), ("noise_ratio", "Noise ratio", "fraction"),
                    ("fscore", "F-score", "fraction"), ("collisions", "Collisions", "count"))
STAGES = ("geometry", "plan", "synthesize", "lift", "export", "evaluate")


def geometry_rows(scene: SceneStore, config: RunConfig) -> list[dict[str, Any]]:
    metrics = scene.require_complete(EVALUATE).attrs.get("metrics", {})
    rows = []
    for key, name, unit in GEOMETRY_METRICS:
        if key in metrics:
            rows.append(row("V", name, float(metrics[key]), unit, note="2 cm threshold, vs. true surfaces"))
        else:
            rows.append(row("V", name, status="unavailable", note="needs ground-truth surfaces (simulation scenes)"))
    return rows


def runtime_rows(scene: SceneStore, iterations: int) -> list[dict[str, Any]]:
    """``Runtime`` (minutes: the total step time / 60; the paper reports 4.79 min per scene), then the
    seconds of each stage as ``time: <stage>``."""

    def secs(step, k=None) -> float:
        st = scene.status(step, k)
        return float(st.attrs.get("seconds", 0.0)) if st.complete else 0.0

    each = range(1, iterations + 1)
    stages = {"geometry": secs(GEOMETRY), "plan": sum(secs(PLAN, k) for k in each),
              "synthesize": sum(secs(SYNTHESIZE, k) for k in each), "lift": sum(secs(LIFT, k) for k in each),
              "export": secs(EXPORT), "evaluate": secs(EVALUATE)}
    note = ("total step execution time / 60 (no orchestration) over " + ", ".join(STAGES)
            + "; the paper reports 4.79 min per scene")
    return ([row("V", "Runtime", sum(stages.values()) / 60.0, "min", note=note)]
            + [row("V", f"time: {name}", stages[name], "s") for name in STAGES])


def planning_rows(scene: SceneStore, config: RunConfig, iterations: int) -> list[dict[str, Any]]:
    """Table V: the exploration geometry, then the runtime."""
    return geometry_rows(scene, config) + runtime_rows(scene, iterations)


def scene_rows(scene: SceneStore, config: RunConfig) -> list[dict[str, Any]]:
    """All per-scene rows of the evaluation suite."""
    iterations = scene_iterations(scene)
    rows = (synthesis_rows(scene, config, iterations) + camera_rows(scene, config, iterations)
            + gaussian_rows(scene) + planning_rows(scene, config, iterations))
    for r in rows:
        r["scene_id"] = scene.scene_id
    return rows


def score(ctx: StepContext) -> dict[str, Any]:
    """The score step: one scene's rows of the evaluation suite."""
    return {"rows": scene_rows(ctx.scene, ctx.config)}


def score_scene(store_uri: str, scene_id: str, config: RunConfig, run_id: str) -> list[dict[str, Any]]:
    """Run (or read back) the score step of an explored scene: its rows."""
    attrs = steps.execute_attrs(store_uri, scene_id, STEPS["score"], config, run_id, score)
    return [dict(r) for r in attrs["rows"]]


# -- table II: over all scenes ---------------------------------------------------------------------
def distribution_rows(store_uri: str, scene_ids: list[str], config: RunConfig) -> list[dict[str, Any]]:
    """FID (frames) and FVD (clips) of the synthesized clips against the reference clips of all scenes.

    Needs reference clips (simulation scenes) and the official Inception / I3D weights; otherwise the
    rows say which is missing. Frames are read scene by scene: table I's frames of every clip
    (:func:`scored_frames`).
    """
    store = open_store(store_uri)

    def clips() -> tuple[list[np.ndarray], list[np.ndarray]]:
        real, fake = [], []
        for sid in scene_ids:
            scene = store.scene(sid)
            for k in range(1, scene_iterations(scene) + 1):
                idx = scored_frames(len(scene.read(PLAN, k, "trajectory")), config.evaluation)[0]
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

    rows: list[dict[str, Any]] = []
    loaded: tuple[list[np.ndarray], list[np.ndarray]] | None = None
    for metric in ("FID", "FVD"):
        try:
            fidfvd.require_weights(metric, config.weights_dir)
        except MetricUnavailable as exc:
            rows.append(row("II", metric, status="unavailable", note=str(exc)))
            continue
        loaded = loaded or clips()
        real = [c.astype(np.float32) / 255.0 for c in loaded[0]]
        fake = [c.astype(np.float32) / 255.0 for c in loaded[1]]
        if len(fake) < 2:
            rows.append(row("II", metric, status="unavailable", note=f"needs at least 2 clips (have {len(fake)})"))
            continue
        # "gram" is the exact Frechet distance through the samples' Gram matrix: milliseconds for few
        # samples, where sqrtm of the 2048x2048 covariance product takes ~25 s on 2 cores.
        if metric == "FID":
            a, b = np.concatenate(real), np.concatenate(fake)
            value = fidfvd.fid(a, b, config.weights_dir, method="gram" if len(a) < 2048 else "sqrtm")
        else:
            value = fidfvd.fvd(np.stack(real), np.stack(fake), config.weights_dir,
                               method="gram" if len(real) < 400 else "sqrtm")
        rows.append(row("II", metric, value, None, note="; ".join(x for x in (f"{len(fake)} clips", note) if x)))
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
                        backend: str, labels: list[str | None] | None = None) -> str:
    """The paper-shaped tables (one per ``TABLES`` entry: scenes as rows, metrics as columns), ending with a
    line saying where Table VI (the 3DGS ablation) is. ``labels``: the scenes' run labels
    (``readers.scene_run_label``: generated scenes and scanned worlds differ); default the generated scenes'."""

    lines = ["# navcrafter evaluation", ""]
    if backend == "simulation":
        label = "; ".join(dict.fromkeys(x for x in labels or [] if x)) or simulation_label()
        lines += [f"> **{label}.** Scores measure the pipeline on simulated ground truth, not learned models.", ""]
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
    return "\n".join(lines + [ABLATION_LINE, ""])
