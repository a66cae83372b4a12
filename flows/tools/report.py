"""Manifest rows, run summaries and status views (what users read about a run)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import PurePath
from typing import Any

from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import EVALUATE, FIT, PLAN, REFINE
from navcrafter.schemas.store import SceneStore
from navcrafter.schemas.tables import utcnow
from navcrafter.tasks.backends import run_label
from navcrafter.tasks.common import open_store
from navcrafter.tasks.readers import read_manifest, scene_run_label  # noqa: F401  (read_manifest re-exported: the CLI and flows read it here)
from navcrafter.tasks.runner import scene_steps


@dataclass
class SceneResult:
    """What a scene run reports back (small: no arrays)."""

    scene_id: str
    sources: list[str]
    status: str  # done | failed
    step: str | None = None
    error: str | None = None
    backend: str = ""
    seconds: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)
    peaks: dict[str, dict[str, float | None]] = field(default_factory=dict)  # step -> peak_rss_mb, peak_gpu_mb
    metrics: dict[str, float] = field(default_factory=dict)
    outputs: str | None = None
    notes: list[str] = field(default_factory=list)  # what a reader of the summary must know (e.g. a skipped term)
    # the run's label (tasks.backends.run_label), read once per scene by scene_result; not in the manifest rows
    label: str | None = field(default=None, compare=False)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class SceneSummary:
    """A scene's run as its store shows it, read once (``scene_summary``): the run summary's row (``scene_result``)
    and the scene's dashboard (``flows.tools.dashboard``) render it."""

    scene_id: str
    steps: int  # steps of the run (``tasks.runner.scene_steps``)
    done: int  # of them complete
    last_step: str | None  # the last step of the unbroken complete prefix
    timings: dict[str, float]  # execution seconds of every complete step, then evaluate
    peaks: dict[str, dict[str, float | None]]  # step -> peak_rss_mb, peak_gpu_mb (steps that measured them)
    gaussians: dict[str, float]  # gs_psnr, gs_gaussians (gs_peak_rss_mb) of the run's final Gaussians
    notes: list[str]  # what a reader must know (e.g. a skipped loss term)
    evaluated: bool  # the evaluate step completed
    evaluation: dict[str, float]  # its metrics ({} before it completed)
    label: str | None  # the run's label (``tasks.backends.run_label``)


def scene_summary(scene: SceneStore, config: RunConfig, label: str | None = None) -> SceneSummary:
    """The summary of a scene's run with ``config``: its steps' statuses, each read once. ``label``: the run's
    label when the caller has it (default ``scene_run_label``: a scanned world's names the scan). The final
    Gaussians are the refine step's when the run refines, else the fit's (none when the run does not fit or the
    step has not completed)."""
    steps = scene_steps(config)
    statuses = [scene.status(step.spec, step.k) for step in steps]
    evaluate = scene.status(EVALUATE)
    completed = [st for st in [*statuses, evaluate] if st.complete]
    last = None
    for step, st in zip(steps, statuses):
        if not st.complete:
            break
        last = step.path
    gaussians: dict[str, float] = {}
    notes: list[str] = []
    fit = scene.status(FIT) if config.fit.enabled else None
    fitted = scene.status(REFINE) if fit is not None and config.refine.enabled else fit
    if fitted is not None and fitted.complete:
        a = fitted.attrs
        gaussians = {"gs_psnr": float(a["psnr"]), "gs_gaussians": float(a["n_gaussians"])}
        if a.get("peak_rss_mb") is not None:
            gaussians["gs_peak_rss_mb"] = float(a["peak_rss_mb"])
        note = fit.attrs.get("lpips_note", "")
        if "skipped" in note:
            notes.append(f"3DGS fit: {note}")
    return SceneSummary(
        scene.scene_id, len(steps), sum(st.complete for st in statuses), last,
        {st.path: float(st.attrs.get("seconds", 0.0)) for st in completed},
        {st.path: {m: st.attrs.get(m) for m in ("peak_rss_mb", "peak_gpu_mb")}
         for st in completed if "peak_rss_mb" in st.attrs},
        gaussians, notes, evaluate.complete,
        {k: float(v) for k, v in evaluate.attrs.get("metrics", {}).items()} if evaluate.complete else {},
        label or scene_run_label(scene, config))


def scene_result(scene: SceneStore, sources: list[str], config: RunConfig, status: str,
                 **fields: Any) -> SceneResult:
    """A scene's result as its store shows it (``scene_summary``): the last complete step, the steps' timings and
    their sum, peaks, the final Gaussians' metrics beside ``fields``' metrics."""
    summary = scene_summary(scene, config, fields.pop("label", None))
    result = SceneResult(scene.scene_id, sources, status, step=summary.last_step, backend=config.backend,
                         seconds=sum(summary.timings.values()), timings=summary.timings, peaks=summary.peaks,
                         label=summary.label, **fields)
    if summary.gaussians:
        result.metrics = {**result.metrics, **summary.gaussians}
    result.notes.extend(summary.notes)
    return result


def write_manifest(store_uri: str, rows: list[dict[str, Any]]) -> None:
    now = utcnow()
    open_store(store_uri).tables.write("manifest", [{"updated_at": now, **r} for r in rows])


def manifest_rows_for(result: SceneResult, run_id: str) -> list[dict[str, Any]]:
    return [{"source": s, "scene_id": result.scene_id, "status": result.status, "step": result.step,
             "error": result.error, "backend": result.backend, "run_id": run_id, "seconds": result.seconds,
             "timings": result.timings, "metrics": result.metrics,
             "n_points": int(result.metrics["n_points"]) if "n_points" in result.metrics else None,
             "outputs": result.outputs} for s in result.sources]


# --------------------------------------------------------------------------------------------------
# Summaries
# --------------------------------------------------------------------------------------------------
def _fmt(v: float | None, unit: str = "", digits: int = 3) -> str:
    return "" if v is None else f"{v:.{digits}f}{unit}"


SUMMARY_COLUMNS = ("image", "scene", "status", "points", "median dist. to true surface", "seen", "coverage",
                   "coverage 5 cm", "noise ratio", "F-score", "collisions", "3DGS PSNR", "seconds", "outputs / error")
_TEXT_COLUMNS = {"image", "scene", "status", "outputs / error"}
EXPORT_FILES = "cloud.ply, video.mp4, trajectory.json, trajectory.parquet"


def summary_rows(results: list[SceneResult]) -> list[tuple[str, ...]]:
    """One row of display strings per result, in ``SUMMARY_COLUMNS`` order."""
    rows = []
    for r in results:
        m = r.metrics
        note = r.outputs if r.status == "done" else (r.error or "")
        rows.append((PurePath(r.sources[0]).name, r.scene_id[:12] if r.scene_id else "-", r.status,
                     str(int(m["n_points"])) if "n_points" in m else "", _fmt(m.get("cloud_median_dist_m"), " m", 4),
                     _fmt(m.get("seen")), _fmt(m.get("coverage")), _fmt(m.get("coverage_at_0.05")),
                     _fmt(m.get("noise_ratio")), _fmt(m.get("fscore")),
                     str(int(m["collisions"])) if "collisions" in m else "", _fmt(m.get("gs_psnr"), " dB", 2),
                     f"{r.seconds:.1f}", note or ""))
    return rows


def results_label(config: RunConfig, results: list[SceneResult]) -> str | None:
    """The run's label: the distinct labels the scene summaries carry (read once per scene: generated scenes and
    scanned worlds differ), else from the config."""
    return "; ".join(dict.fromkeys(r.label for r in results if r.label)) or run_label(config)


def summary_header(run_id: str, config: RunConfig, results: list[SceneResult]) -> list[str]:
    done = sum(r.status == "done" for r in results)
    lines = []
    label = results_label(config, results)
    if config.backend == "simulation":
        lines.append(f"{label}. Distances are measured against the true scene surfaces.")
    elif label:
        lines.append(f"{label}.")
    lines.append(f"Run {run_id}: {done} of {len(results)} images done; backend '{config.backend}', "
                 f"{config.iterations} iterations of {config.synthesis.num_frames} frames at "
                 f"{config.synthesis.width}x{config.synthesis.height}.")
    if config.fit.enabled:
        f = config.fit
        size = f"{f.resolution} px" if f.resolution else "the frames' size"
        lines.append(f"3DGS: {f.iterations} iterations at {size}, loss L1 + "
                     f"{f.lambda_lpips:g} LPIPS + {f.lambda_depth:g} depth ({f.depth_space} depth); 3DGS PSNR is "
                     f"on held-out synthesized frames{' after refinement' if config.refine.enabled else ''}.")
    for note in dict.fromkeys(n for r in results for n in r.notes):
        lines.append(note)
    return lines


def summary_markdown(run_id: str, config: RunConfig, results: list[SceneResult]) -> str:
    header = summary_header(run_id, config, results)
    lines = ["# navcrafter run summary", ""]
    if results_label(config, results):
        lines += [f"> **{header.pop(0)}**", ""]
    lines += header + ["", "| " + " | ".join(SUMMARY_COLUMNS) + " |",
                       "|" + "|".join("---" if c in _TEXT_COLUMNS else "---:" for c in SUMMARY_COLUMNS) + "|"]
    for row in summary_rows(results):
        cells = [c.replace("|", "/").replace("\n", " ") for c in row]
        cells[1] = f"`{cells[1]}`"
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_summary(store_uri: str, run_id: str, config: RunConfig, results: list[SceneResult]) -> str:
    store = open_store(store_uri)
    md = summary_markdown(run_id, config, results)
    doc = {"run_id": run_id, "backend": config.backend, "config": config.model_dump(mode="json"),
           "scenes": [r.to_dict() for r in results]}
    if label := results_label(config, results):
        doc["label"] = label
    store.write_bytes(f"runs/{run_id}/summary.json", json.dumps(doc, indent=1, default=str).encode())
    store.write_bytes(f"runs/{run_id}/summary.md", md.encode())
    return md


def plan_artifact_markdown(store_uri: str, scene_id: str, k: int) -> str | None:
    """Dashboard view of a planner step: the top-down plot (embedded) and the candidates' table."""
    import base64


    scene = open_store(store_uri).scene(scene_id)
    st = scene.status(PLAN, k)
    if not st.complete or "topdown.png" not in st.attrs.get("files", {}):
        return None
    png = open_store(store_uri).read_bytes(st.attrs["files"]["topdown.png"]["path"])
    arrays = scene.read_all(PLAN, k)
    a = st.attrs
    lines = [f"# Plan, iteration {k} ({a['strategy']})", "",
             f"chosen candidate: {a['chosen']}; optimised: {a.get('optimised')}; fallback: "
             f"{a.get('fallback') or 'none'}; candidate draws: {a.get('rounds')}; "
             f"planning time: {a.get('seconds', 0):.2f} s", "",
             f"![top-down](data:image/png;base64,{base64.b64encode(png).decode()})", "",
             "| candidate | score F | collides |", "|---:|---:|---|"]
    for i, (sc, col) in enumerate(zip(arrays.get("candidate_scores", []), arrays.get("candidate_collides", []))):
        lines.append(f"| {i} | {sc:.3f} | {'yes' if col else 'no'} |")
    return "\n".join(lines) + "\n"
