"""The ``onnx`` backend's Synthesizer: the exported camera-controlled Wan2.1 I2V sampled with onnxruntime.

``OnnxSynthesizer(model_dir, synthesis_config)`` turns a ``SynthesisRequest`` into the sampler's inputs:

* **Plücker rays** ``[T, H, W, 6]`` of ``request.trajectory`` with ``request.intrinsics``
  (``models.camera.cameras.plucker_rays``) in the convention the camera control was trained with (manifest
  ``config.plucker_convention``, required: a manifest without it is refused, never given a default; a run
  config's ``synthesis.plucker_convention``, when set, must equal it);
* the **extra reference frame**: ``request.reference_image`` (the scene's input photo, for clips that start
  elsewhere) with the rays of ``request.reference_c2w`` in the clip's Plücker frame (same origin and scale as the
  trajectory's: ``cameras.clip_relative_rays``); without one the sampler uses the conditioning image at
  ``trajectory[0]``;
* **point-cloud renders and visibility masks**: the current cloud splatted along the trajectory with
  ``models.reconstruction.pointrender.render_points`` (nearest point per pixel, z-buffered). The world-space point
  size defaults to ``POINT_SIZE_FACTOR`` (1.5) times the cloud's median nearest-neighbour spacing (a KD-tree over
  at most 20k sampled points; on a fused cloud this is about the fusion voxel, so neighbouring points close up into a
  surface without bleeding over depth edges; ``render_points`` caps the splat at ``max_radius`` 3 px), or the
  ``point_size`` given to the constructor;
* the request image, and the text embeddings stored in the model directory at export time;

and runs ``pipeline.sample_video`` with an ``OrtRunner``, seeded with ``request.seed``.

**fun-camera** (``synthesis.model = "fun-camera"``; ``funcamera/``): the manifest must record ``config.model``
``"fun-camera"`` (architecture ``wan2.1-fun-v1.1-control-camera``) and the run's ``synthesis.model`` must name the
model the directory holds, else ``SynthesizerModelError``. Its rays are ``funcamera.fun_camera_plucker`` (VideoX-Fun's
convention, recorded as ``"videox-fun"``; ``synthesis.plucker_convention`` must stay unset), and it takes neither
point-cloud renders nor the extra reference frame (``request.cloud_*`` and ``request.reference_*`` are unused).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from navcrafter.models.camera.cameras import PLUCKER_CONVENTIONS, clip_relative_rays, plucker_rays
from navcrafter.models.roles import SynthesisRequest
from navcrafter.models.synthesis.pipeline import (
    OrtRunner,
    SamplerConfig,
    SynthesisShapeError,
    sample_video,
    sampler_settings,
)

POINT_SIZE_FACTOR = 1.5


class PluckerConventionError(SynthesisShapeError):
    """The model directory's Plücker convention is missing, unknown or not the run's (the message names the fix)."""


class SynthesizerModelError(SynthesisShapeError):
    """The model directory holds another synthesizer model than the run's ``synthesis.model``."""

_SPACING_SAMPLE = 20_000


def cloud_spacing(points: np.ndarray, seed: int = 0) -> float:
    """Median nearest-neighbour distance of a cloud (on a seeded sample of at most 20k points)."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < 2:
        return 0.0
    if len(pts) > _SPACING_SAMPLE:
        # The sample is sparser than the cloud: measure sample->cloud distances instead of sample->sample.
        idx = np.random.RandomState(seed).choice(len(pts), _SPACING_SAMPLE, replace=False)
        d, _ = cKDTree(pts).query(pts[idx], k=2)
    else:
        d, _ = cKDTree(pts).query(pts, k=2)
    nn = d[:, 1]
    nn = nn[nn > 0]
    return float(np.median(nn)) if len(nn) else 0.0


def default_point_size(points: np.ndarray) -> float:
    s = cloud_spacing(points)
    return POINT_SIZE_FACTOR * s if s > 0 else 1e-3


class OnnxSynthesizer:
    """``Synthesizer`` role on an exported model directory (``export.export_synthesizer``)."""

    backend = "onnx"

    def __init__(self, model_dir: str | Path, synthesis_config, providers: list[str] | None = None,
                 point_size: float | None = None) -> None:
        self.model_dir = Path(model_dir)
        self.runner = OrtRunner(self.model_dir, providers, offload=bool(getattr(synthesis_config, "offload", False)))
        self.config = synthesis_config
        self.point_size = point_size
        mcfg = self.runner.config
        have = (int(mcfg["num_frames"]), int(mcfg["height"]), int(mcfg["width"]))
        want = (synthesis_config.num_frames, synthesis_config.height, synthesis_config.width)
        if have != want:
            raise SynthesisShapeError(
                f"the synthesizer in {self.model_dir} was exported for num_frames={have[0]}, height={have[1]}, "
                f"width={have[2]}, but the run config asks for num_frames={want[0]}, height={want[1]}, "
                f"width={want[2]}: set synthesis.num_frames/height/width to the exported values or re-export "
                f"with export_synthesizer(..., num_frames={want[0]}, height={want[1]}, width={want[2]})")
        self.model_name = self._model(mcfg, getattr(synthesis_config, "model", "navcrafter"))
        self.convention = self._convention(mcfg, getattr(synthesis_config, "plucker_convention", None))
        self.text_emb, self.neg_text_emb = self.runner.text_embeddings()

    def _model(self, mcfg: dict, wanted: str) -> str:
        """The model the directory holds (manifest ``config.model``; absent: NavCrafter's), which must be the run's
        ``synthesis.model``."""
        # deferred: diffusers loads with funcamera only when a synthesizer is opened, not on import
        from navcrafter.models.synthesis import funcamera

        have = mcfg.get("model", "navcrafter")
        architecture = self.runner.manifest.get("architecture")
        if (have == funcamera.MODEL_NAME) != (architecture == funcamera.ARCHITECTURE) or have not in (
                "navcrafter", funcamera.MODEL_NAME):
            raise SynthesizerModelError(f"the synthesizer in {self.model_dir} records model {have!r} with "
                                        f"architecture {architecture!r}: re-export it with this navcrafter version")
        if have != wanted:
            export = ("export_fun_camera (models/zoo/exporters.py)" if wanted == funcamera.MODEL_NAME
                      else "navcrafter models export-synthesizer")
            raise SynthesizerModelError(
                f"the run config asks for synthesis.model={wanted!r}, but the synthesizer in {self.model_dir} is "
                f"{have!r} (architecture {architecture!r}): set synthesis.model={have!r} or export a {wanted!r} "
                f"synthesizer there ({export})")
        return have

    def _convention(self, mcfg: dict, wanted: str | None) -> str:
        """The weights' recorded Plücker convention (manifest), checked against the run's when it sets one."""
        # deferred: diffusers loads with funcamera only when a synthesizer is opened, not on import
        from navcrafter.models.synthesis import funcamera

        have = mcfg.get("plucker_convention")
        if self.model_name == funcamera.MODEL_NAME:
            if have != funcamera.PLUCKER_CONVENTION:
                raise PluckerConventionError(f"the fun-camera synthesizer in {self.model_dir} records "
                                             f"plucker_convention={have!r}, not {funcamera.PLUCKER_CONVENTION!r}: "
                                             f"re-export it with this navcrafter version")
            if wanted is not None:
                raise PluckerConventionError(
                    f"synthesis.plucker_convention={wanted!r} selects the rays of NavCrafter's camera control; the "
                    f"fun-camera model in {self.model_dir} takes VideoX-Fun's own ({funcamera.PLUCKER_CONVENTION!r}, "
                    f"funcamera.fun_camera_plucker): unset synthesis.plucker_convention")
            return have
        if have is None:
            raise PluckerConventionError(
                f"the synthesizer in {self.model_dir} records no plucker_convention in its manifest config, so the "
                f"camera rays its weights were trained with are unknown: re-export it with this navcrafter version "
                f"(export_synthesizer / navcrafter models export-synthesizer records the camera control's)")
        if have not in PLUCKER_CONVENTIONS:
            raise PluckerConventionError(f"the synthesizer in {self.model_dir} records plucker_convention="
                                         f"{have!r}, not one of {list(PLUCKER_CONVENTIONS)}: re-export it")
        if wanted is not None and wanted != have:
            raise PluckerConventionError(
                f"the run config asks for synthesis.plucker_convention={wanted!r}, but the camera control in "
                f"{self.model_dir} was trained with {have!r}: unset synthesis.plucker_convention (use the weights' "
                f"own) or export weights trained with {wanted!r}")
        return have

    def sampler_config(self, seed: int) -> SamplerConfig:
        return sampler_settings(self.config, seed, self.runner.config.get("scheduler"))

    def _check(self, request: SynthesisRequest) -> tuple[int, int, int]:
        c = self.config
        T, H, W = c.num_frames, c.height, c.width
        traj = np.asarray(request.trajectory)
        if traj.ndim != 3 or traj.shape[1:] != (4, 4):
            raise SynthesisShapeError(f"request.trajectory must be [T, 4, 4], got {traj.shape}")
        if traj.shape[0] != T:
            raise SynthesisShapeError(
                f"the request has a {traj.shape[0]}-pose trajectory but the synthesizer in {self.model_dir} "
                f"makes num_frames={T} clips: plan trajectories of synthesis.num_frames={T} poses (or re-export "
                f"the model with export_synthesizer(..., num_frames={traj.shape[0]}) and set synthesis.num_frames)")
        img = np.asarray(request.image)
        if img.shape != (H, W, 3):
            raise SynthesisShapeError(
                f"request.image is {img.shape}, the synthesizer makes {H}x{W} frames (synthesis.height={H}, "
                f"synthesis.width={W}): resize the working image to {W}x{H} or change synthesis.height/width "
                f"and re-export")
        K = request.intrinsics
        if (K.width, K.height) != (W, H):
            raise SynthesisShapeError(f"request.intrinsics are for {K.width}x{K.height}, the frames are {W}x{H} "
                                      f"(synthesis.width/height): scale them with Intrinsics.resize({W}, {H})")
        if (request.reference_image is None) != (request.reference_c2w is None):
            raise SynthesisShapeError("request.reference_image and request.reference_c2w come together (the input "
                                      "photo and its world camera-to-world); got only one of them")
        if request.reference_image is not None:
            ref = np.asarray(request.reference_image)
            if ref.shape != (H, W, 3):
                raise SynthesisShapeError(f"request.reference_image is {ref.shape}, the synthesizer makes {H}x{W} "
                                          f"frames: resize it to {W}x{H} like the conditioning image")
            if np.asarray(request.reference_c2w).shape != (4, 4):
                raise SynthesisShapeError(f"request.reference_c2w must be [4, 4], got "
                                          f"{np.asarray(request.reference_c2w).shape}")
        return T, H, W

    def conditions(self, request: SynthesisRequest) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                             np.ndarray | None, np.ndarray | None]:
        """(Plücker rays ``[T, H, W, 6]``, renders uint8 ``[T, H, W, 3]``, visibility bool ``[T, H, W]``, reference
        image uint8 ``[H, W, 3]`` or None, its rays ``[1, H, W, 6]`` or None).

        The reference's rays are in the trajectory's Plücker frame (``clip_relative_rays``: for "relative" the
        trajectory's first camera is the origin and its scale normalises the reference translation too); None
        when the request has no reference (the sampler then uses the conditioning image at ``trajectory[0]``).
        """
        # deferred: torch loads only when conditions are rendered (importing this module stays torch-free)
        from navcrafter.models.reconstruction.pointrender import render_points

        T, H, W = self._check(request)
        K = request.intrinsics.K
        traj = np.asarray(request.trajectory, dtype=np.float64)
        if self.model_name == "fun-camera":  # rays only: no render condition, no reference frame (funcamera/)
            # deferred: diffusers loads with funcamera only for the fun-camera model
            from navcrafter.models.synthesis.funcamera import fun_camera_plucker

            return (fun_camera_plucker(traj, K, H, W), np.zeros((T, H, W, 3), dtype=np.uint8),
                    np.zeros((T, H, W), dtype=bool), None, None)
        plucker = plucker_rays(traj, K, H, W, convention=self.convention)
        ref_image = ref_plucker = None
        if request.reference_image is not None:
            ref_image = np.asarray(request.reference_image, dtype=np.uint8)
            ref_plucker = clip_relative_rays(traj, np.asarray(request.reference_c2w, dtype=np.float64)[None], K, H,
                                             W, convention=self.convention)
        renders = np.zeros((T, H, W, 3), dtype=np.uint8)
        masks = np.zeros((T, H, W), dtype=bool)
        pts = np.asarray(request.cloud_points, dtype=np.float32).reshape(-1, 3)
        if len(pts):
            cols = np.asarray(request.cloud_colors, dtype=np.uint8).reshape(-1, 3)
            if len(cols) != len(pts):
                raise SynthesisShapeError(f"request.cloud_colors has {len(cols)} rows for {len(pts)} points")
            size = self.point_size if self.point_size is not None else default_point_size(pts)
            for i in range(T):
                r = render_points(pts, traj[i], K, H, W, size, colors=cols)
                renders[i], masks[i] = r.color, r.mask
        return plucker, renders, masks, ref_image, ref_plucker

    def synthesize(self, request: SynthesisRequest) -> np.ndarray:
        """Frames ``[T, H, W, 3]`` uint8 following ``request.trajectory``."""
        plucker, renders, masks, ref_image, ref_plucker = self.conditions(request)
        return sample_video(self.runner, np.asarray(request.image, dtype=np.uint8), plucker, renders, masks,
                            self.text_emb, self.neg_text_emb, self.sampler_config(request.seed),
                            reference_image=ref_image, reference_plucker=ref_plucker)
