"""Dashboard view of one scene: thumbnails of its input image, of the planner's top-down plots and of
frames of every synthesized clip, and its metrics, as one Markdown document with embedded PNGs.

A pure function of the store (published by the scene flow as a Prefect artifact; tested without
Prefect). Every image is small: thumbnails have at most ``THUMB`` pixels on their longer side, the
render grid at most ``GRID_MAX``, and photos are reduced to a 128-colour palette, so a scene's
document stays at some tens of kB. Renders of the simulation backend are labelled SIMULATION.
"""

from __future__ import annotations

import base64
import io
from pathlib import PurePath

import numpy as np
from PIL import Image, ImageDraw

from navcrafter.flows.tools.report import scene_summary
from navcrafter.models.simulation.worlds import SCAN_KIND
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.layout import INGEST, PLAN, SYNTHESIZE
from navcrafter.tasks.backends import label_band, run_band
from navcrafter.tasks.common import open_store
from navcrafter.tasks.readers import truth_scene

THUMB = 256  # longer side of a thumbnail (input image, top-down plots), pixels
GRID_MAX = 512  # longer side of the render grid, pixels
FRAMES_PER_CLIP = 4  # frames shown per synthesized clip: first, evenly spaced, last


def png_data_uri(img: Image.Image, palette: bool = False) -> str:
    """``data:image/png;base64,...`` of an image (optionally reduced to an adaptive 128-colour palette)."""
    if palette:
        img = img.convert("RGB").quantize(colors=128, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE)
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def thumbnail(img: Image.Image, size: int = THUMB) -> Image.Image:
    img = img.copy()
    img.thumbnail((size, size), Image.Resampling.LANCZOS)
    return img


def clip_frame_indices(num_frames: int, count: int = FRAMES_PER_CLIP) -> list[int]:
    return sorted({int(round(i)) for i in np.linspace(0, num_frames - 1, min(count, num_frames))})


def render_grid(
    clips: list[tuple[int, np.ndarray, list[int]]], label: str | None, max_side: int = GRID_MAX
) -> Image.Image:
    """One row per clip (``(k, frames [F,H,W,3], frame indices)``) under a caption naming them, and an
    optional label band (e.g. SIMULATION) across the top."""
    cols = max(len(f) for _, f, _ in clips)
    H, W = clips[0][1].shape[1:3]
    caption, band, gap = 12, (14 if label else 0), 2
    cell = max(16, min(THUMB, (max_side - gap * (cols - 1)) // cols, W))
    ch = max(1, round(cell * H / W))
    rows_h = len(clips) * (ch + caption + gap)
    scale = min(1.0, max_side / (band + rows_h))  # many iterations: shrink the cells to fit
    cell, ch = max(16, int(cell * scale)), max(1, int(ch * scale))
    width = cols * cell + gap * (cols - 1)
    grid = Image.new("RGB", (width, band + len(clips) * (ch + caption + gap)), (255, 255, 255))
    draw = ImageDraw.Draw(grid)
    if label:
        draw.rectangle([0, 0, width, band - 1], fill=(200, 30, 30))
        draw.text((4, 1), label, fill=(255, 255, 255))
    y = band
    for k, frames, idx in clips:
        draw.text((2, y), f"iteration {k}: frames {', '.join(map(str, idx))}", fill=(0, 0, 0))
        for c, frame in enumerate(frames):
            img = Image.fromarray(frame).resize((cell, ch), Image.Resampling.LANCZOS)
            grid.paste(img, (c * (cell + gap), y + caption))
        y += ch + caption + gap
    return grid


def _metric(name: str, value: float) -> str:
    if name in ("n_points", "collisions"):
        return f"{int(value):,}".replace(",", " ")
    if name.endswith("_m"):
        return f"{value:.4f} m"
    if name.endswith("_seconds"):
        return f"{value:.2f} s"
    return f"{value:.3f}"


def scene_dashboard_markdown(store_uri: str, scene_id: str, config: RunConfig, label: str | None = None) -> str:
    """Markdown of a scene's input, top-down trajectory plots, render grid and metrics (whatever of
    them is complete in the store: a failed scene shows what it got to). Its steps, metrics and label are the
    scene's summary (``report.scene_summary``)."""
    store = open_store(store_uri)
    scene = store.scene(scene_id)
    short = scene_id[:12]
    inp = scene.status(INGEST)
    sim = config.backend == "simulation"
    summary = scene_summary(scene, config, label)  # the flow passes the run summary's label, read once per scene
    label = summary.label
    scan = sim and (truth_scene(scene) or {}).get("kind") == SCAN_KIND
    source = PurePath(inp.attrs.get("source", "")).name or short
    lines = [f"# Scene `{short}`: {source}", ""]
    if label:
        lines += [f"> **{label}.**", ""]
    lines += [
        f"{summary.done} of {summary.steps} steps complete; backend '{config.backend}', {config.iterations} iterations "
        f"of {config.synthesis.num_frames} frames at {config.synthesis.width}x{config.synthesis.height}.",
        "",
    ]
    if inp.complete:
        image = Image.fromarray(scene.read(INGEST, None, "image"))
        lines += [
            "## Input" + ((" (demo render of a scanned world)" if scan else " (demo render of a generated scene)")
                          if sim else ""),
            "",
            f"![input image]({png_data_uri(thumbnail(image), palette=True)})",
            "",
        ]
    plots = []
    for k in range(1, config.iterations + 1):
        st = scene.status(PLAN, k)
        info = st.attrs.get("files", {}).get("topdown.png") if st.complete else None
        if info:
            plot = thumbnail(Image.open(io.BytesIO(store.read_bytes(info["path"]))))
            plots.append(f"![top-down plan, iteration {k}]({png_data_uri(plot, palette=True)})")
    if plots:
        lines += [
            "## Trajectories (top-down; blue: final path, grey: before collision optimisation)",
            "",
            " ".join(plots),
            "",
        ]
    clips = []
    for k in range(1, config.iterations + 1):
        st = scene.status(SYNTHESIZE, k)
        if st.complete:
            n = int(st.attrs.get("num_frames") or config.synthesis.num_frames)
            idx = clip_frame_indices(n)
            clips.append((k, scene.read_rows(SYNTHESIZE, k, "frames", idx), idx))
    if clips:
        band = label_band(label) if label else run_band(config)
        grid = render_grid(clips, band)
        title = "## Synthesized views" + (" (SIMULATION: ground-truth renders, not a learned model)" if sim else
                                          f" ({label})" if label else "")
        lines += [title, "", f"![render grid]({png_data_uri(grid, palette=True)})", ""]
    if summary.evaluated:
        lines += [
            "## Metrics" + (" (simulation: against the true scene)" if sim else ""),
            "",
            "| metric | value |",
            "|---|---:|",
        ]
        lines += [f"| {name} | {_metric(name, v)} |" for name, v in sorted(summary.evaluation.items())]
        lines.append("")
    return "\n".join(lines)
