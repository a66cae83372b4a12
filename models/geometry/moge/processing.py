"""Pre- and post-processing outside the graph, as the official ``infer()``: the token grid and resize of the input,
the head maps resized once to the input size and remapped (``head_maps_to_size``), focal and z-shift recovery, metric
scale and mask (``postprocess``); ``infer_torch`` runs the whole pipeline on the torch model."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

if TYPE_CHECKING:
    from navcrafter.models.geometry.moge.config import MoGe2Config
    from navcrafter.models.geometry.moge.model import MoGe2


def num_tokens_for_level(level: int, num_tokens_range: tuple[int, int] = (1200, 3600)) -> int:
    """Official ``resolution_level`` (0..9) -> number of tokens; level 9 (the official default) = the maximum."""
    lo, hi = num_tokens_range
    return int(lo + (level / 9) * (hi - lo))


def token_grid(height: int, width: int, num_tokens: int) -> tuple[int, int]:
    """Token rows and columns for ``num_tokens`` at the image's aspect ratio (official rounding)."""
    aspect = width / height
    return max(1, round((num_tokens / aspect) ** 0.5)), max(1, round((num_tokens * aspect) ** 0.5))


def _resize_antialias(array: np.ndarray, height: int, width: int) -> np.ndarray:
    """[h, w, C] float -> [height, width, C] float32: bilinear with antialiasing when shrinking (PIL's
    triangle filter, the same as torch ``interpolate(bilinear, antialias=True)``)."""
    from PIL import Image

    channels = [np.asarray(Image.fromarray(np.ascontiguousarray(array[..., c], dtype=np.float32), mode="F")
                           .resize((width, height), Image.BILINEAR)) for c in range(array.shape[-1])]
    return np.stack(channels, axis=-1).astype(np.float32)


def preprocess_image(image: np.ndarray, num_tokens: int, patch_size: int = 14) -> np.ndarray:
    """``[H, W, 3]`` uint8 (or float in [0, 1]) -> ``[1, 3, 14*rows, 14*cols]`` float32 in [0, 1], resized
    (bilinear, antialiased, as the official encoder) to the token grid of ``token_grid``. The ImageNet
    mean/std normalisation is part of the network."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"expected an [H, W, 3] image, got shape {image.shape}")
    x = image.astype(np.float32) / 255.0 if image.dtype == np.uint8 else image.astype(np.float32)
    rows, cols = token_grid(image.shape[0], image.shape[1], num_tokens)
    x = _resize_antialias(x, rows * patch_size, cols * patch_size)
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None])


def _view_plane_uv_np(height: int, width: int) -> np.ndarray:
    diagonal = math.hypot(height, width)
    u = (2 * np.arange(width) + 1 - width) / diagonal
    v = (2 * np.arange(height) + 1 - height) / diagonal
    return np.stack(np.meshgrid(u, v, indexing="xy"), axis=-1).astype(np.float32)


def _nearest_index(n_in: int, n_out: int) -> np.ndarray:
    """torch ``interpolate(mode="nearest")`` source indices (float32 arithmetic, as torch)."""
    return np.minimum(np.floor(np.arange(n_out, dtype=np.float32) * np.float32(n_in / n_out)).astype(np.int64),
                      n_in - 1)


def recover_focal_shift(points: np.ndarray, valid: np.ndarray, focal: float | None = None,
                        size: tuple[int, int] = (64, 64)) -> tuple[float, float]:
    """The official focal/z-shift recovery: on a nearest-downsampled (64x64) map, least-squares
    ``min |focal * xy / (z + shift) - uv|`` over the valid pixels (``focal`` relative to half the image
    diagonal). Returns ``(focal, shift)``; ``(1, 0)`` when fewer than 2 pixels are valid."""
    from scipy.optimize import least_squares

    height, width = points.shape[:2]
    ri, ci = _nearest_index(height, size[0]), _nearest_index(width, size[1])
    uv = _view_plane_uv_np(height, width)[ri][:, ci]
    pts = points[ri][:, ci]
    keep = valid[ri][:, ci]
    # float32 maps and float64 shift, as official (``solve_optimal_focal_shift``): with ``ftol=1e-3`` the
    # solver's stopping point depends on the arithmetic, so it is kept the same
    uv, xy, z = uv[keep].astype(np.float32), pts[keep][:, :2].astype(np.float32), pts[keep][:, 2].astype(np.float32)
    if len(z) < 2:
        return 1.0, 0.0

    def focal_of(shift):
        proj = xy / (z + shift)[:, None]
        return (proj * uv).sum() / np.square(proj).sum()

    def residual(shift):
        proj = xy / (z + shift)[:, None]
        f = focal if focal is not None else (proj * uv).sum() / np.square(proj).sum()
        return (f * proj - uv).ravel()

    shift = np.float32(least_squares(residual, x0=0, ftol=1e-3, method="lm").x.squeeze())
    return (float(focal_of(shift)) if focal is None else float(focal)), float(shift)


def remap_points(points: torch.Tensor, kind: str) -> torch.Tensor:
    """The official ``_remap_points`` of the raw points map ``[..., 3]`` (``exp``: ``z = exp(z')``, ``xy = xy' z``)."""
    if kind == "sinh":
        return torch.sinh(points)
    if kind == "exp":
        xy, z = points.split([2, 1], dim=-1)
        z = torch.exp(z)
        return torch.cat([xy * z, z], dim=-1)
    if kind == "sinh_exp":
        xy, z = points.split([2, 1], dim=-1)
        return torch.cat([torch.sinh(xy), torch.exp(z)], dim=-1)
    if kind != "linear":
        raise ValueError(f"unknown remap_output {kind!r}")
    return points


def head_maps_to_size(points_raw: np.ndarray, mask_logits: np.ndarray, normal_raw: np.ndarray | None, *,
                      size: tuple[int, int], remap_output: str = "exp"
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """One image's raw head maps (``points_raw [h,w,3]``, ``mask_logits [h,w]``, ``normal_raw [h,w,3]``, at
    the heads' resolution) -> ``(points [H,W,3], mask [H,W] probability, normal [H,W,3] unit)`` at ``size``
    = (H, W), float32: resized once (torch bilinear, ``align_corners=False``, no antialias), then remapped,
    with the official ``forward``'s ops in its order."""
    parts = [np.asarray(points_raw, np.float32), np.asarray(mask_logits, np.float32)[..., None]]
    if normal_raw is not None:
        parts.append(np.asarray(normal_raw, np.float32))
    maps = torch.from_numpy(np.concatenate(parts, axis=-1)).permute(2, 0, 1)[None]
    with torch.no_grad():
        maps = F.interpolate(maps, size=tuple(size), mode="bilinear", align_corners=False, antialias=False)
        maps = maps[0].permute(1, 2, 0)
        points = remap_points(maps[..., :3], remap_output)
        mask = maps[..., 3].sigmoid()
        normal = F.normalize(maps[..., 4:], dim=-1) if normal_raw is not None else None
    return points.numpy(), mask.numpy(), None if normal is None else normal.numpy()


def outputs_to_result(outputs: dict[str, np.ndarray], size: tuple[int, int], config: MoGe2Config,
                      fov_x: float | None = None, index: int = 0) -> MoGe2Result:
    """Batch item ``index`` of the network's outputs (``MoGe2.output_names``) -> ``MoGe2Result`` at ``size``:
    ``head_maps_to_size`` then ``postprocess`` (the torch and onnxruntime paths share this)."""
    points, mask, normal = head_maps_to_size(
        outputs["points_raw"][index], outputs["mask_logits"][index],
        outputs["normal_raw"][index] if "normal_raw" in outputs else None, size=size,
        remap_output=config.remap_output)
    scale = float(outputs["metric_scale"][index]) if "metric_scale" in outputs else None
    return postprocess(points, mask, scale, normal, fov_x=fov_x)


def infer_torch(model: MoGe2, image: np.ndarray, num_tokens: int | None = None,
                fov_x: float | None = None) -> MoGe2Result:
    """The whole MoGe-2 pipeline in torch (float32) for one ``[H, W, 3]`` image (uint8, or float in [0, 1]),
    as the official ``infer(image, num_tokens, fov_x=fov_x, use_fp16=False)``: token-grid resize, network with
    the original aspect ratio, one resize of the head maps to ``H x W``, focal/shift recovery, metric scale."""
    image = np.asarray(image)
    num_tokens = int(num_tokens or num_tokens_for_level(9, model.config.num_tokens_range))
    x = preprocess_image(image, num_tokens, model.config.patch_size)
    aspect = torch.tensor([image.shape[1] / image.shape[0]], dtype=torch.float32)
    param = next(model.parameters())
    with torch.no_grad():
        out = model(torch.from_numpy(x).to(param.device, param.dtype), aspect.to(param.device))
    arrays = {k: v.float().cpu().numpy() for k, v in zip(model.output_names, out)}
    return outputs_to_result(arrays, image.shape[:2], model.config, fov_x=fov_x)


@dataclass
class MoGe2Result:
    """One image's geometry at the input resolution (the official ``infer()`` outputs, plus inverse depth)."""

    depth: np.ndarray  # [H, W] float32 metric z-depth (relative without a scale head); inf = invalid
    inv_depth: np.ndarray  # [H, W] float32 1 / depth; 0 = invalid
    valid: np.ndarray  # [H, W] bool: mask >= 0.5, finite, positive depth; ~valid = sky / no geometry
    points: np.ndarray  # [H, W, 3] float32 camera-space points (OpenCV; re-projected from depth); inf = invalid
    intrinsics: np.ndarray  # [3, 3] float32 normalised (fx, fy in units of width, height; centre 0.5, 0.5)
    normal: np.ndarray | None  # [H, W, 3] float32 unit normals (OpenCV camera frame); 0 = invalid
    metric_scale: float


def postprocess(points: np.ndarray, mask: np.ndarray, metric_scale: float | None = None,
                normal: np.ndarray | None = None, *, size: tuple[int, int] | None = None,
                fov_x: float | None = None) -> MoGe2Result:
    """Remapped maps of one image at the input resolution (``points [H,W,3]``, ``mask [H,W]`` probability,
    ``metric_scale``, ``normal [H,W,3]``; see ``head_maps_to_size``) -> ``MoGe2Result``. ``size``, when
    given, must be the maps' size (the maps are never resized here: the official pipeline resizes the raw
    head maps once, before the remaps).

    As official: ``valid = mask > 0.5``, focal and z-shift are recovered from
    the point map (or only the shift, when ``fov_x`` in degrees is known), ``depth = (z + shift) * scale``,
    pixels with ``depth <= 0`` are invalid. Non-finite values are invalid too. Invalid pixels get
    ``depth = inf``, ``inv_depth = 0``, ``points = inf``, ``normal = 0``.
    """
    height, width = mask.shape[:2]
    if size is not None and tuple(size) != (height, width):
        raise ValueError(f"postprocess: maps are {height}x{width} but size is {tuple(size)}; resize the raw head "
                         f"maps with head_maps_to_size first (one resize, then the remaps, as official)")
    if points.shape[:2] != (height, width) or (normal is not None and normal.shape[:2] != (height, width)):
        raise ValueError(f"postprocess: points {points.shape} / normal maps differ in size from mask {mask.shape}")
    points = points.astype(np.float32)
    valid = (mask > 0.5) & np.isfinite(points).all(axis=-1)
    aspect = width / height
    known = None
    if fov_x is not None:
        known = aspect / math.sqrt(1 + aspect**2) / math.tan(math.radians(fov_x) / 2)
    safe_points = np.where(valid[..., None], points, 0.0)
    focal, shift = recover_focal_shift(safe_points, valid, focal=known)
    fx = focal / 2 * math.sqrt(1 + aspect**2) / aspect
    fy = focal / 2 * math.sqrt(1 + aspect**2)
    intrinsics = np.array([[fx, 0, 0.5], [0, fy, 0.5], [0, 0, 1]], dtype=np.float32)
    scale = 1.0 if metric_scale is None else float(metric_scale)
    with np.errstate(invalid="ignore", over="ignore"):
        depth = (points[..., 2] + np.float32(shift)) * np.float32(scale)
    valid &= np.isfinite(depth) & (depth > 0) & np.isfinite(scale)
    depth = np.where(valid, depth, np.inf).astype(np.float32)
    with np.errstate(divide="ignore"):
        inv_depth = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0).astype(np.float32)
    u = ((np.arange(width) + 0.5) / width - 0.5) / fx
    v = ((np.arange(height) + 0.5) / height - 0.5) / fy
    rays = np.stack([*np.meshgrid(u, v, indexing="xy"), np.ones((height, width))], axis=-1)
    with np.errstate(invalid="ignore"):
        cam = np.where(valid[..., None], rays * np.where(valid, depth, 0.0)[..., None], np.inf).astype(np.float32)
    if normal is not None:
        norm = np.linalg.norm(normal, axis=-1, keepdims=True)
        normal = np.where(valid[..., None] & (norm > 0), normal / np.maximum(norm, 1e-12), 0.0).astype(np.float32)
    return MoGe2Result(depth=depth, inv_depth=inv_depth, valid=valid, points=cam, intrinsics=intrinsics,
                       normal=normal, metric_scale=scale)
