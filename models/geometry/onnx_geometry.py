"""Geometry role on onnxruntime: an exported VGGT (``export_geometry``) behind the ``Geometry`` protocol."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from navcrafter.models.camera.cameras import Intrinsics
from navcrafter.models.geometry import processing as proc
from navcrafter.models.roles import GeometryPrediction
from navcrafter.models.runtime import onnxio


class OnnxGeometry:
    """Cameras, depth and confidence of ``S`` frames from one VGGT forward pass on onnxruntime.

    ``predict`` resizes the frames to the model input (official ``crop`` rule by default), runs the graph,
    converts the pose encoding to camera-to-world poses re-expressed in the first camera's frame
    (``c2w[0]`` is exactly the identity), takes the intrinsics and depth/confidence maps back to the
    input frames' pixels, and maps confidence to [0, 1] (``processing.confidence_to_unit``). The
    ``hint_*`` arguments are ignored (a learned model estimates cameras from pixels); the model is
    deterministic, so ``seed`` has no effect.
    """

    backend = "onnx"

    def __init__(self, model_dir: Path, providers: list[str] | None = None, mode: str = "crop") -> None:
        self.model_dir = Path(model_dir)
        self.manifest = onnxio.load_manifest(self.model_dir, "geometry")
        if self.manifest.get("architecture") != "vggt":
            raise onnxio.ModelDirError(f"{self.model_dir}: geometry architecture "
                                       f"{self.manifest.get('architecture')!r} is not 'vggt'")
        if "geometry" not in self.manifest.get("graphs", {}):
            raise onnxio.ModelDirError(f"{self.model_dir}: the manifest names no 'geometry' graph; re-export")
        cfg = self.manifest["config"]
        self.img_size = int(cfg["img_size"])
        self.patch_size = int(cfg["patch_size"])
        self.mode = mode
        self.random_weights = onnxio.is_random_weights(self.manifest)
        self.runner = onnxio.GraphRunner(self.model_dir, self.manifest, providers)

    def run_raw(self, images: np.ndarray) -> dict[str, np.ndarray]:
        """The graph's outputs for model input ``images [S, 3, h, w]`` float32 in [0, 1] (batch of one)."""
        images = np.ascontiguousarray(images, dtype=np.float32)[None]
        return self.runner.run("geometry", {"images": images})

    def predict(self, frames: np.ndarray, *, seed: int, hint_c2w: np.ndarray | None = None,
                hint_intrinsics: Intrinsics | None = None, hint_depth=None) -> GeometryPrediction:
        frames = np.asarray(frames)
        images, tr = proc.preprocess_frames(frames, self.img_size, self.patch_size, self.mode)
        out = self.run_raw(images)
        pose_enc = np.asarray(out["pose_enc"][0], dtype=np.float64)  # [S, 9]
        h, w = images.shape[-2:]

        # cameras: w2c in the model's first-camera frame -> c2w, re-based exactly on the first camera
        q_norm = np.linalg.norm(pose_enc[:, 3:7], axis=-1)
        degenerate = ~(np.isfinite(pose_enc).all(axis=-1) & (q_norm > 1e-8))
        pose_enc = pose_enc.copy()
        pose_enc[degenerate] = (0, 0, 0, 0, 0, 0, 1, 1.0, 1.0)  # identity, ~57 deg FoV, flagged in extras
        fov = np.clip(pose_enc[:, 7:9], np.deg2rad(1.0), np.deg2rad(179.0))
        pose_enc[:, 7:9] = fov
        extrinsics, K_model = proc.pose_encoding_to_extri_intri(pose_enc, (h, w))
        c2w_model = proc.extrinsics_to_c2w(extrinsics)
        c2w = proc.relative_to_first(c2w_model)
        K = tr.intrinsics_to_source(K_model)

        # depth / confidence at the model resolution -> input frames
        depth = out["depth"][0, ..., 0]
        conf = proc.confidence_to_unit(out["depth_conf"][0])
        depth, conf = proc.clean_depth(depth, conf)
        depth, conf = proc.resample_to_source(depth, conf, tr)

        first = c2w_model[0]
        rot_cos = np.clip((np.trace(first[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
        valid = depth > 0
        extras = {
            "first_pose_rotation_deg": float(np.rad2deg(np.arccos(rot_cos))),
            "first_pose_translation": float(np.linalg.norm(first[:3, 3])),
            "degenerate_poses": float(degenerate.sum()),
            "valid_fraction": float(valid.mean()),
            "mean_confidence": float(conf[valid].mean()) if valid.any() else 0.0,
            "fov_x_deg_mean": float(np.rad2deg(fov[:, 1]).mean()),
            "model_width": float(w),
            "model_height": float(h),
        }
        return GeometryPrediction(c2w=c2w, K=K, depth=depth, confidence=conf, extras=extras)
