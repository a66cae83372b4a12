"""Plots for the dashboard and the store (PIL only)."""

from __future__ import annotations

import io

import numpy as np


def topdown_png(cloud_points: np.ndarray, cloud_colors: np.ndarray, state, result, strategy: str, k: int,
                size: int = 480) -> bytes:
    """Top-down view (world x right, world z up the image; world up is -y) of the cloud, the scene
    centre, the candidates (red cross: collides; green: chosen; label: score), the trajectory before
    (grey) and after (blue) collision optimisation, and the current camera (black)."""
    from PIL import Image, ImageDraw

    def xz(p: np.ndarray) -> np.ndarray:
        return np.asarray(p)[..., [0, 2]]

    marks = np.concatenate([xz(result.candidates[:, :3, 3]), xz(result.trajectory[:, :3, 3]),
                            xz(result.initial_trajectory[:, :3, 3]), xz(state.centre[None])])
    cloud_xz = xz(cloud_points)
    keep = np.zeros(len(cloud_xz), dtype=bool)
    if len(cloud_xz):
        lo_c, hi_c = np.percentile(cloud_xz, 2, axis=0), np.percentile(cloud_xz, 98, axis=0)
        keep = ((cloud_xz >= lo_c) & (cloud_xz <= hi_c)).all(1)
        marks = np.concatenate([marks, lo_c[None], hi_c[None]])
    lo, hi = marks.min(0), marks.max(0)
    span = float(max(hi - lo)) * 1.1 + 1e-6
    mid = (lo + hi) / 2

    def px(p: np.ndarray) -> np.ndarray:
        q = (np.asarray(p) - mid) / span
        return np.stack([(0.5 + q[..., 0]) * size, (0.5 - q[..., 1]) * size], -1)

    img = Image.new("RGB", (size, size), (250, 250, 247))
    arr = np.asarray(img).copy()
    idx = np.flatnonzero(keep)
    if len(idx) > 60000:
        idx = idx[np.linspace(0, len(idx) - 1, 60000).astype(int)]
    if len(idx):
        c = px(cloud_xz[idx]).astype(int)
        ok = (c >= 0).all(1) & (c < size).all(1)
        arr[c[ok, 1], c[ok, 0]] = (0.55 * cloud_colors[idx][ok] + 0.45 * 250).astype(np.uint8)
    img = Image.fromarray(arr)
    draw = ImageDraw.Draw(img)
    draw.line([tuple(p) for p in px(xz(result.initial_trajectory[:, :3, 3]))], fill=(150, 150, 150), width=2)
    draw.line([tuple(p) for p in px(xz(result.trajectory[:, :3, 3]))], fill=(30, 90, 220), width=3)
    cx, cy = px(xz(state.centre))
    draw.line([(cx - 6, cy), (cx + 6, cy)], fill=(0, 0, 0), width=2)
    draw.line([(cx, cy - 6), (cx, cy + 6)], fill=(0, 0, 0), width=2)
    for i, (c2w, score, col) in enumerate(zip(result.candidates, result.scores, result.collides)):
        x, y = px(xz(c2w[:3, 3]))
        if col:
            draw.line([(x - 5, y - 5), (x + 5, y + 5)], fill=(210, 30, 30), width=2)
            draw.line([(x - 5, y + 5), (x + 5, y - 5)], fill=(210, 30, 30), width=2)
        else:
            colour = (20, 160, 60) if i == result.chosen else (240, 150, 20)
            draw.ellipse([x - 5, y - 5, x + 5, y + 5], fill=colour, outline=(0, 0, 0))
        draw.text((x + 7, y - 6), f"{score:.2f}", fill=(0, 0, 0))
    x, y = px(xz(state.current[:3, 3]))
    draw.rectangle([x - 4, y - 4, x + 4, y + 4], fill=(0, 0, 0))
    note = f"iteration {k}, {strategy}; chosen {result.chosen}"
    if result.fallback:
        note += f", fallback: {result.fallback}"
    draw.text((6, 4), note, fill=(0, 0, 0))
    draw.text((6, 16), "grey: interpolated path  blue: final path  x: collides  green: NBV", fill=(60, 60, 60))
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()
