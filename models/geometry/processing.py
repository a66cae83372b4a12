"""Pre- and post-processing shared by the geometry backends (VGGT conventions), numpy only.

Input (official VGGT ``load_and_preprocess_images``):

* ``mode="crop"`` (the official default): resize to width ``img_size`` (518), height scaled with the
  aspect ratio and rounded to a multiple of the patch size (14), bicubic (PIL); if the height then
  exceeds ``img_size``, the central ``img_size`` rows are kept.
* ``mode="pad"``: the longer side becomes ``img_size``, the other is scaled and rounded to a multiple
  of 14, and the image is padded with white (1.0) to ``img_size`` x ``img_size``, centred.
* The network takes RGB in [0, 1] (it normalises with the ImageNet mean/std itself).

``InputTransform`` records the mapping between source and model pixels (an axis-aligned scale and
offset of pixel *edges*), so intrinsics and per-pixel maps can be taken back to the source frames.

Cameras (``absT_quaR_FoV`` pose encoding, 9 numbers per frame): translation ``t`` (3), quaternion
``(x, y, z, w)`` (scalar last, 4), field of view ``(fov_h, fov_w)`` in radians (2). ``(R(q), t)`` is the
OpenCV **world-to-camera** transform (``extrinsics`` 3x4), the world being the first camera's frame;
intrinsics have ``fy = (H / 2) / tan(fov_h / 2)``, ``fx = (W / 2) / tan(fov_w / 2)`` and a centred
principal point ``(W / 2, H / 2)`` in model pixels. navcrafter stores camera-to-world 4x4 float64.

Confidence: VGGT's confidences are ``1 + exp(x) >= 1``. ``confidence_to_unit`` maps them to [0, 1)
with ``1 - 1 / conf`` (0 at the minimum 1, 0.5 at conf 2, -> 1 as conf grows); values below 1 or
non-finite map to 0. A pixel whose depth is non-finite or not positive is invalid: depth 0,
confidence 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from navcrafter.models.camera.cameras import quat_wxyz_to_matrix

TARGET_SIZE = 518
PATCH_SIZE = 14


# --------------------------------------------------------------------------------------------------
# Input geometry
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class InputTransform:
    """Model pixel edge coordinates ``x_m = scale_x * x_src + offset_x`` (same for y)."""

    src_width: int
    src_height: int
    width: int  # model input size
    height: int
    scale_x: float
    scale_y: float
    offset_x: float
    offset_y: float
    resized_width: int  # size after resizing, before crop / pad
    resized_height: int
    mode: str

    @property
    def matrix(self) -> np.ndarray:
        """3x3 affine taking source pixel coordinates to model pixel coordinates."""
        return np.array([[self.scale_x, 0.0, self.offset_x], [0.0, self.scale_y, self.offset_y], [0.0, 0.0, 1.0]])

    def intrinsics_to_source(self, K: np.ndarray) -> np.ndarray:
        """Intrinsics ``[..., 3, 3]`` in model pixels → the same cameras in source pixels."""
        return np.linalg.inv(self.matrix) @ np.asarray(K, dtype=np.float64)

    def intrinsics_to_model(self, K: np.ndarray) -> np.ndarray:
        return self.matrix @ np.asarray(K, dtype=np.float64)


def _round_to(value: float, multiple: int) -> int:
    return max(multiple, int(round(value / multiple)) * multiple)


def vggt_input_transform(width: int, height: int, img_size: int = TARGET_SIZE, patch_size: int = PATCH_SIZE,
                         mode: str = "crop") -> InputTransform:
    """Where a ``width`` x ``height`` frame lands in the model input (official crop / pad rules)."""
    if width <= 0 or height <= 0:
        raise ValueError(f"frame size must be positive, got {width}x{height}")
    if mode == "crop":
        rw = img_size
        rh = _round_to(height * (rw / width), patch_size)
        out_w, out_h = rw, min(rh, img_size)
        off_x, off_y = 0.0, -float((rh - img_size) // 2) if rh > img_size else 0.0
    elif mode == "pad":
        if width >= height:
            rw, rh = img_size, _round_to(height * (img_size / width), patch_size)
        else:
            rh, rw = img_size, _round_to(width * (img_size / height), patch_size)
        rw, rh = min(rw, img_size), min(rh, img_size)
        out_w = out_h = img_size
        off_x, off_y = float((img_size - rw) // 2), float((img_size - rh) // 2)
    else:
        raise ValueError(f"mode must be 'crop' or 'pad', got {mode!r}")
    return InputTransform(src_width=int(width), src_height=int(height), width=int(out_w), height=int(out_h),
                          scale_x=rw / width, scale_y=rh / height, offset_x=off_x, offset_y=off_y,
                          resized_width=int(rw), resized_height=int(rh), mode=mode)


def preprocess_frames(frames: np.ndarray, img_size: int = TARGET_SIZE, patch_size: int = PATCH_SIZE,
                      mode: str = "crop") -> tuple[np.ndarray, InputTransform]:
    """uint8 frames ``[S, H, W, 3]`` → model input ``[S, 3, h, w]`` float32 in [0, 1] and the transform.

    Bicubic resize with PIL on the uint8 image (as the official loader), then crop or white padding.
    """
    from PIL import Image

    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] == 0:
        raise ValueError(f"frames must be [S, H, W, 3] with S >= 1, got shape {frames.shape}")
    if frames.dtype != np.uint8:
        raise ValueError(f"frames must be uint8, got {frames.dtype}")
    S, H, W, _ = frames.shape
    tr = vggt_input_transform(W, H, img_size, patch_size, mode)
    out = np.ones((S, 3, tr.height, tr.width), dtype=np.float32)
    x0, y0 = int(tr.offset_x), int(tr.offset_y)
    for i in range(S):
        img = Image.fromarray(frames[i]).resize((tr.resized_width, tr.resized_height), Image.Resampling.BICUBIC)
        arr = np.asarray(img, dtype=np.float32).transpose(2, 0, 1) / 255.0
        if mode == "crop":
            out[i] = arr[:, -y0:-y0 + tr.height, :]
        else:
            out[i, :, y0:y0 + tr.resized_height, x0:x0 + tr.resized_width] = arr
    return out, tr


# --------------------------------------------------------------------------------------------------
# Rotations (quaternions x, y, z, w: scalar last, as VGGT)
# --------------------------------------------------------------------------------------------------
def quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternions ``[..., 4]`` in VGGT's order (x, y, z, w; need not be unit) -> rotation matrices ``[..., 3, 3]``
    (``models.camera.cameras.quat_wxyz_to_matrix`` on the reordered quaternion)."""
    q = np.asarray(q, dtype=np.float64)
    return quat_wxyz_to_matrix(np.concatenate([q[..., 3:], q[..., :3]], axis=-1))


def mat_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` → unit quaternions ``[..., 4]`` (x, y, z, w) with ``w >= 0``.

    Takes, per matrix, the best conditioned of the four standard solutions (largest diagonal term).
    """
    R = np.asarray(R, dtype=np.float64)
    batch = R.shape[:-2]
    m = R.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    cand = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    best = np.argmax(cand, axis=1)
    q = np.empty((m.shape[0], 4))
    for i, b in enumerate(best):
        r = m[i]
        if b == 0:
            s = 2.0 * np.sqrt(max(1.0 + tr[i], 1e-300))
            q[i] = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
        elif b == 1:
            s = 2.0 * np.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 1e-300))
            q[i] = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
        elif b == 2:
            s = 2.0 * np.sqrt(max(1.0 + r[1, 1] - r[0, 0] - r[2, 2], 1e-300))
            q[i] = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
        else:
            s = 2.0 * np.sqrt(max(1.0 + r[2, 2] - r[0, 0] - r[1, 1], 1e-300))
            q[i] = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return q.reshape(batch + (4,))


# --------------------------------------------------------------------------------------------------
# Pose encoding <-> extrinsics / intrinsics
# --------------------------------------------------------------------------------------------------
def pose_encoding_to_extri_intri(pose_enc: np.ndarray, image_size_hw: tuple[int, int]
                                 ) -> tuple[np.ndarray, np.ndarray]:
    """``pose_enc [..., 9]`` → world-to-camera ``extrinsics [..., 3, 4]`` and ``intrinsics [..., 3, 3]``
    (model pixels of an ``image_size_hw`` image), float64."""
    pe = np.asarray(pose_enc, dtype=np.float64)
    if pe.shape[-1] != 9:
        raise ValueError(f"pose encoding must have 9 values per camera, got shape {pe.shape}")
    H, W = image_size_hw
    R = quat_xyzw_to_matrix(pe[..., 3:7])
    extrinsics = np.concatenate([R, pe[..., :3, None]], axis=-1)
    K = np.zeros(pe.shape[:-1] + (3, 3))
    K[..., 0, 0] = (W / 2.0) / np.tan(pe[..., 8] / 2.0)
    K[..., 1, 1] = (H / 2.0) / np.tan(pe[..., 7] / 2.0)
    K[..., 0, 2] = W / 2.0
    K[..., 1, 2] = H / 2.0
    K[..., 2, 2] = 1.0
    return extrinsics, K


def extri_intri_to_pose_encoding(extrinsics: np.ndarray, intrinsics: np.ndarray,
                                 image_size_hw: tuple[int, int]) -> np.ndarray:
    """World-to-camera ``extrinsics [..., 3, 4]`` (or 4x4) and ``intrinsics [..., 3, 3]`` → ``[..., 9]``.
    (The principal point is not encoded: VGGT assumes it centred.)"""
    E = np.asarray(extrinsics, dtype=np.float64)
    K = np.asarray(intrinsics, dtype=np.float64)
    H, W = image_size_hw
    quat = mat_to_quat(E[..., :3, :3])
    fov_h = 2.0 * np.arctan((H / 2.0) / K[..., 1, 1])
    fov_w = 2.0 * np.arctan((W / 2.0) / K[..., 0, 0])
    return np.concatenate([E[..., :3, 3], quat, fov_h[..., None], fov_w[..., None]], axis=-1)


def extrinsics_to_c2w(extrinsics: np.ndarray) -> np.ndarray:
    """World-to-camera ``[..., 3, 4]`` → camera-to-world ``[..., 4, 4]`` float64 (rotation inverted by
    transposition; the rotation must be orthonormal, as ``quat_xyzw_to_matrix`` returns)."""
    E = np.asarray(extrinsics, dtype=np.float64)
    R, t = E[..., :3, :3], E[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    c2w = np.zeros(E.shape[:-2] + (4, 4))
    c2w[..., :3, :3] = Rt
    c2w[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    c2w[..., 3, 3] = 1.0
    return c2w


def c2w_to_extrinsics(c2w: np.ndarray) -> np.ndarray:
    """Camera-to-world ``[..., 4, 4]`` → world-to-camera ``[..., 3, 4]``."""
    c2w = np.asarray(c2w, dtype=np.float64)
    Rt = np.swapaxes(c2w[..., :3, :3], -1, -2)
    t = -np.einsum("...ij,...j->...i", Rt, c2w[..., :3, 3])
    return np.concatenate([Rt, t[..., None]], axis=-1)


def relative_to_first(c2w: np.ndarray) -> np.ndarray:
    """Re-express camera-to-world poses ``[S, 4, 4]`` in the first camera's frame; ``out[0]`` is exactly I."""
    c2w = np.asarray(c2w, dtype=np.float64)
    first_inv = np.linalg.inv(c2w[0])
    out = first_inv[None] @ c2w
    out[:, 3, :] = (0.0, 0.0, 0.0, 1.0)
    out[0] = np.eye(4)
    return out


# --------------------------------------------------------------------------------------------------
# Confidence and validity
# --------------------------------------------------------------------------------------------------
def confidence_to_unit(conf: np.ndarray) -> np.ndarray:
    """VGGT confidence (``1 + exp(x) >= 1``) → [0, 1): ``1 - 1 / conf``; < 1 or non-finite → 0."""
    c = np.asarray(conf, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(np.isfinite(c) & (c >= 1.0), 1.0 - 1.0 / c, 0.0)
    return out.astype(np.float32)


def invalid_depth_mask(depth: np.ndarray) -> np.ndarray:
    """True where depth is non-finite or not positive."""
    d = np.asarray(depth)
    return ~(np.isfinite(d) & (d > 0))


def clean_depth(depth: np.ndarray, confidence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth 0 and confidence 0 wherever depth is invalid (float32 both)."""
    bad = invalid_depth_mask(depth)
    d = np.where(bad, 0.0, depth).astype(np.float32)
    c = np.where(bad, 0.0, confidence).astype(np.float32)
    return d, c


def resample_to_source(depth: np.ndarray, confidence: np.ndarray, tr: InputTransform
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Model-grid ``depth`` / ``confidence`` ``[S, h, w]`` (invalid = depth 0) → the source frames ``[S, H, W]``.

    Bilinear at the source pixel centres, averaging only valid model pixels (weights renormalised);
    source pixels outside the model input (cropped away) or with no valid neighbour get depth 0,
    confidence 0.
    """
    depth = np.asarray(depth, dtype=np.float64)
    confidence = np.asarray(confidence, dtype=np.float64)
    S, h, w = depth.shape
    xs = tr.scale_x * (np.arange(tr.src_width) + 0.5) + tr.offset_x  # model coordinates of source centres
    ys = tr.scale_y * (np.arange(tr.src_height) + 0.5) + tr.offset_y
    inside_x = (xs >= 0) & (xs <= w)
    inside_y = (ys >= 0) & (ys <= h)
    fx = np.clip(xs - 0.5, 0.0, w - 1.0)
    fy = np.clip(ys - 0.5, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(fx).astype(int), w - 1)
    y0 = np.minimum(np.floor(fy).astype(int), h - 1)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    ax, ay = fx - x0, fy - y0
    valid = (depth > 0).astype(np.float64)
    num_d = np.zeros((S, tr.src_height, tr.src_width))
    num_c = np.zeros_like(num_d)
    den = np.zeros_like(num_d)
    for yy, wy in ((y0, 1 - ay), (y1, ay)):
        for xx, wx in ((x0, 1 - ax), (x1, ax)):
            wgt = wy[:, None] * wx[None, :]
            v = valid[:, yy][:, :, xx] * wgt
            num_d += depth[:, yy][:, :, xx] * v
            num_c += confidence[:, yy][:, :, xx] * v
            den += v
    ok = (den > 1e-12) & inside_y[None, :, None] & inside_x[None, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(ok, num_d / den, 0.0)
        c = np.where(ok, num_c / den, 0.0)
    return d.astype(np.float32), np.clip(c, 0.0, 1.0).astype(np.float32)
