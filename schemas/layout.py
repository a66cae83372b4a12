"""Zarr v3 layout of a scene: the single source of truth for every stored array.

A store holds ``scenes/<scene_id>/`` (``scene_id`` = sha256 of the input image's bytes). Each pipeline
step owns one group, described by a ``StepSpec``: its arrays (dtype, symbolic shape, chunking) and the
attributes it must set. A step writes a fresh group, and sets ``complete = true`` in the group's
attributes last; readers trust a group only when it is complete (see ``schemas.store``).

Symbolic dimensions:

====  =========================================================================
H0,W0 normalised input image (longer side <= ``ingest.max_side``)
H,W   working resolution (``synthesis.height`` x ``synthesis.width``)
T     frames of one synthesized clip (``synthesis.num_frames``)
S     views passed to the geometry model by one lift step (``<= lift.max_views``)
N     points of the fused scene cloud after a step
C     candidate poses considered by the planner
G,B   Gaussians of the fitted 3DGS scene; higher SH bases per channel
F,V   frames used by the fit; of them held out
h,w   the fit's resolution; M frames with depth supervision; I training iterations
====  =========================================================================

Scene tree::

    scenes/<scene_id>/            attrs: scene_id, source
      input/                      step "ingest"
      iter_0/geometry/            step "geometry": initial cameras, depth and cloud of the input view
      iter_<k>/plan/              step "plan" (k = 1..N): trajectory for iteration k
      iter_<k>/synthesize/        step "synthesize": frames along the trajectory
      iter_<k>/lift/              step "lift": geometry of the frames, fused cloud after iteration k
      gaussians/                  step "fit": 3DGS scene, cameras, held-out evaluation (when fit.enabled)
      exports/                    step "export": files (cloud.ply, video.mp4, trajectory.json/.parquet)

The scene cloud after iteration k is the ``cloud_*`` arrays of ``iter_k/lift`` (``iter_0/geometry`` for
k = 0): each step carries the cumulative cloud it produced, so resuming never needs a separate merge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

SCHEMA_VERSION = 1
CLOUD_CHUNK_ROWS = 262_144

COMMON_ATTRS = ("step", "complete", "key", "exec_id", "backend", "started_at", "finished_at",
                "seconds", "schema_version")


@dataclass(frozen=True)
class ArraySpec:
    name: str
    dtype: str
    shape: tuple[str | int, ...]
    chunks: tuple[str | int, ...]
    doc: str
    optional: bool = False

    def resolve(self, dims: dict[str, int]) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """Concrete ``(shape, chunks)`` given the sizes of symbolic dimensions."""
        shape = tuple(d if isinstance(d, int) else dims[d] for d in self.shape)
        chunks = []
        for c, s in zip(self.chunks, shape):
            size = c if isinstance(c, int) else s
            if c in ("N", "G"):
                size = min(s, CLOUD_CHUNK_ROWS)
            chunks.append(max(1, min(size, s) if s else 1))
        return shape, tuple(chunks)


@dataclass(frozen=True)
class StepSpec:
    name: str
    path: str  # may contain "{k}"
    doc: str
    arrays: tuple[ArraySpec, ...] = ()
    attrs: tuple[str, ...] = ()
    iterative: bool = False
    extra: dict[str, str] = field(default_factory=dict)

    def group_path(self, k: int | None = None) -> str:
        if self.iterative:
            if k is None or k < 1:
                raise ValueError(f"step {self.name!r} needs an iteration k >= 1, got {k}")
            return self.path.format(k=k)
        if k not in (None, 0):
            raise ValueError(f"step {self.name!r} is not iterative, got k={k}")
        return self.path

    def array(self, name: str) -> ArraySpec:
        for a in self.arrays:
            if a.name == name:
                return a
        raise KeyError(f"step {self.name!r} has no array {name!r}; it has {[a.name for a in self.arrays]}")


def _cloud() -> tuple[ArraySpec, ...]:
    return (
        ArraySpec("cloud_points", "float32", ("N", 3), ("N", 3), "fused scene cloud, world frame"),
        ArraySpec("cloud_colors", "uint8", ("N", 3), ("N", 3), "RGB of each point"),
        ArraySpec("cloud_confidence", "float32", ("N",), ("N",), "fused confidence in [0, 1]"),
    )


INGEST = StepSpec(
    "ingest", "input",
    "The validated, normalised input photo and the working image the models see.",
    arrays=(
        ArraySpec("image", "uint8", ("H0", "W0", 3), ("H0", "W0", 3),
                  "input photo: EXIF-oriented, RGB8, longer side <= ingest.max_side"),
        ArraySpec("work_image", "uint8", ("H", "W", 3), ("H", "W", 3),
                  "centre crop of `image` to the working aspect, resized to H x W"),
    ),
    attrs=("source", "sha256", "original_size", "original_mode", "exif_orientation", "crop_box",
           "normalised_size", "work_size"),
    extra={"simulation_truth": "optional: hidden ground-truth record of demo images (simulation mode)"},
)

GEOMETRY = StepSpec(
    "geometry", "iter_0/geometry",
    "Initial geometry of the input view; defines the world frame (input camera = identity).",
    arrays=(
        ArraySpec("c2w", "float64", (4, 4), (4, 4), "input camera pose (identity by definition)"),
        ArraySpec("K", "float64", (3, 3), (3, 3), "estimated intrinsics of the working image"),
        ArraySpec("depth", "float32", ("H", "W"), ("H", "W"), "z-depth, world units, 0 = invalid"),
        ArraySpec("confidence", "float32", ("H", "W"), ("H", "W"), "per-pixel confidence"),
        *_cloud(),
    ),
    attrs=("n_points",),
    extra={"simulation_world_scale": "simulation only: world units per metre (hidden truth)"},
)

PLAN = StepSpec(
    "plan", "iter_{k}/plan",
    "Camera trajectory of iteration k, from the current pose to the next view, and the planner's state.",
    arrays=(
        ArraySpec("trajectory", "float64", ("T", 4, 4), ("T", 4, 4), "world c2w of every frame"),
        ArraySpec("K", "float64", (3, 3), (3, 3), "intrinsics of every frame"),
        ArraySpec("centre", "float64", (3,), (3,), "scene centre o the cameras look at"),
        ArraySpec("candidates", "float64", ("C", 4, 4), ("C", 4, 4), "candidate poses considered"),
        ArraySpec("candidate_scores", "float64", ("C",), ("C",), "score F of each candidate (higher is better)",
                  optional=True),
        ArraySpec("candidate_collides", "bool", ("C",), ("C",), "collision detector G of each candidate",
                  optional=True),
        ArraySpec("candidate_masks", "bool", ("C", "H", "W"), (1, "H", "W"),
                  "visibility mask of each candidate (cloud splatted into it)", optional=True),
        ArraySpec("initial_trajectory", "float64", ("T", 4, 4), ("T", 4, 4),
                  "trajectory before collision optimisation", optional=True),
    ),
    attrs=("strategy", "chosen"),
    iterative=True,
    extra={"topdown.png": "file: top-down plot of cloud, candidates and trajectories"},
)

SYNTHESIZE = StepSpec(
    "synthesize", "iter_{k}/synthesize",
    "The video clip synthesized along the trajectory of iteration k.",
    arrays=(ArraySpec("frames", "uint8", ("T", "H", "W", 3), (1, "H", "W", 3), "RGB frames"),),
    iterative=True,
)

LIFT = StepSpec(
    "lift", "iter_{k}/lift",
    "Geometry of selected frames aligned to the world, and the scene cloud after iteration k.",
    arrays=(
        ArraySpec("view_index", "int32", ("S",), ("S",), "frame index (into the clip) of each view"),
        ArraySpec("c2w", "float64", ("S", 4, 4), ("S", 4, 4), "estimated world pose of each view"),
        ArraySpec("K", "float64", ("S", 3, 3), ("S", 3, 3), "estimated intrinsics of each view"),
        ArraySpec("depth", "float32", ("S", "H", "W"), (1, "H", "W"), "aligned z-depth, 0 = invalid"),
        ArraySpec("confidence", "float32", ("S", "H", "W"), (1, "H", "W"), "per-pixel confidence"),
        *_cloud(),
    ),
    attrs=("scale", "n_new_points", "n_points"),
    iterative=True,
)

FIT = StepSpec(
    "fit", "gaussians",
    "The 3D Gaussian Splatting scene fitted to the frames (tasks/fit.py), its cameras, held-out evaluation "
    "and loss history. Parameters are 3DGS's raw ones (log-scales, opacity logits, SH), world frame.",
    arrays=(
        ArraySpec("means", "float32", ("G", 3), ("G", 3), "Gaussian centres, world frame"),
        ArraySpec("quats", "float32", ("G", 4), ("G", 4), "rotations, quaternion (w, x, y, z), not normalised"),
        ArraySpec("log_scales", "float32", ("G", 3), ("G", 3), "log of the per-axis standard deviations"),
        ArraySpec("opacity_logits", "float32", ("G",), ("G",), "logit of the opacity"),
        ArraySpec("sh_dc", "float32", ("G", 3), ("G", 3), "degree-0 SH coefficient per RGB channel"),
        ArraySpec("sh_rest", "float32", ("G", "B", 3), ("G", "B", 3),
                  "higher SH bands [G, (degree+1)^2 - 1, 3], coefficient-major (gsplat's layout)"),
        ArraySpec("frame_ref", "int32", ("F", 2), ("F", 2),
                  "(iteration k, frame index in iter_k/synthesize) of each frame of the fit, in order"),
        ArraySpec("c2w", "float64", ("F", 4, 4), ("F", 4, 4), "camera of each frame (the planned pose)"),
        ArraySpec("K", "float64", ("F", 3, 3), ("F", 3, 3), "intrinsics of each frame at the fit resolution"),
        ArraySpec("holdout", "bool", ("F",), ("F",), "frames held out of training (every holdout_every-th)"),
        ArraySpec("holdout_renders", "uint8", ("V", "h", "w", 3), (1, "h", "w", 3),
                  "the fitted model rendered at the held-out cameras"),
        ArraySpec("train", "bool", ("F",), ("F",),
                  "frames trained on: not held out, every fit.train_stride-th of those"),
        ArraySpec("depth_targets", "float32", ("F", "h", "w"), (1, "h", "w"),
                  "calibrated depth supervising each training frame at the fit resolution (0: none)"),
        ArraySpec("depth_calibration", "float64", ("M", 6), ("M", 6),
                  "per depth-supervised frame: (frame, scale s, bias b, inlier fraction, robust sigma, source: "
                  "0 the lift step's geometry depth, 1 the cloud rendered into the frame)"),
        ArraySpec("history", "float32", ("I", 6), ("I", 6),
                  "per iteration: loss, l1, lpips, depth (NaN when off), drop rate, number of Gaussians"),
    ),
    attrs=("n_gaussians", "sh_degree", "resolution", "holdout_every", "n_train", "n_holdout", "psnr", "ssim",
           "lpips", "lpips_note", "init_psnr", "scene_scale", "train_seconds", "final_loss"),
)

REFINE = StepSpec(
    "refine", "renders",
    "Diffusion refinement (tasks/refine.py): the fitted Gaussians rendered at novel cameras off the trajectory, "
    "the Refiner's refined views, and the Gaussians trained further with them as extra views.",
    arrays=(
        ArraySpec("c2w", "float64", ("V", 4, 4), ("V", 4, 4), "novel cameras (OpenCV c2w, world frame)"),
        ArraySpec("K", "float64", (3, 3), (3, 3), "their intrinsics at the fit resolution"),
        ArraySpec("source_frame", "int32", ("V",), ("V",),
                  "the fit frame (index into gaussians/frame_ref) each novel camera was displaced from"),
        ArraySpec("reference_frame", "int32", ("V",), ("V",),
                  "the training frame given to the refiner as reference (the nearest camera)"),
        ArraySpec("renders", "uint8", ("V", "h", "w", 3), (1, "h", "w", 3), "the fitted model at the novel cameras"),
        ArraySpec("refined", "uint8", ("V", "h", "w", 3), (1, "h", "w", 3), "the refiner's output"),
        ArraySpec("means", "float32", ("G", 3), ("G", 3), "refined Gaussians (as in gaussians/)"),
        ArraySpec("quats", "float32", ("G", 4), ("G", 4), "rotations (w, x, y, z)"),
        ArraySpec("log_scales", "float32", ("G", 3), ("G", 3), "log standard deviations"),
        ArraySpec("opacity_logits", "float32", ("G",), ("G",), "logit of the opacity"),
        ArraySpec("sh_dc", "float32", ("G", 3), ("G", 3), "degree-0 SH coefficient"),
        ArraySpec("sh_rest", "float32", ("G", "B", 3), ("G", "B", 3), "higher SH bands"),
        ArraySpec("holdout_renders", "uint8", ("H", "h", "w", 3), (1, "h", "w", 3),
                  "the refined model at the fit's held-out cameras"),
        ArraySpec("history", "float32", ("I", 6), ("I", 6), "per iteration, as gaussians/history"),
    ),
    attrs=("psnr", "ssim", "lpips", "psnr_before", "ssim_before", "n_views", "n_gaussians", "refiner",
           "train_seconds"),
)

EXPORT = StepSpec(
    "export", "exports",
    "User-facing files, stored beside the group's zarr.json; attrs list them with checksums.",
    attrs=("files",),
)

EVALUATE = StepSpec(
    "evaluate", "evaluation",
    "Scene metrics (tasks/scene_metrics.py), kept so that a rerun does not recompute them; also appended "
    "to the metrics table.",
    attrs=("metrics", "iterations"),
)

SCORE = StepSpec(
    "score", "scores",
    "One scene's rows of the evaluation suite (navcrafter evaluate): image metrics, camera guidance "
    "(COLMAP), runtime, geometry; rows in the schema of the evaluations table, kept in attrs.",
    attrs=("rows",),
)

STEPS: dict[str, StepSpec] = {s.name: s for s in (INGEST, GEOMETRY, PLAN, SYNTHESIZE, LIFT, FIT, REFINE, EXPORT,
                                                  EVALUATE, SCORE)}


def scene_group(scene_id: str) -> str:
    return f"scenes/{scene_id}"


def cloud_step(k: int) -> tuple[StepSpec, int | None]:
    """Which step holds the scene cloud after iteration ``k``."""
    return (GEOMETRY, None) if k == 0 else (LIFT, k)


def dependencies(step: str, k: int | None, iterations: int, fit: bool = False,
                 refine: bool = False) -> list[tuple[StepSpec, int | None]]:
    """Upstream steps whose outputs a step reads (their keys enter its cache key); ``fit`` / ``refine``: whether
    the fit / refine steps run (the export then reads them)."""
    if step == "ingest":
        return []
    if step == "geometry":
        return [(INGEST, None)]
    if step == "plan":
        deps = [cloud_step(k - 1)]
        return deps + ([(PLAN, k - 1)] if k and k > 1 else [(GEOMETRY, None)])
    if step == "synthesize":
        return [(INGEST, None), (PLAN, k), cloud_step(k - 1)]
    if step == "lift":
        return [(INGEST, None), (GEOMETRY, None), (PLAN, k), (SYNTHESIZE, k), cloud_step(k - 1)]
    if step in ("fit", "refine", "export"):
        deps: list[tuple[StepSpec, int | None]] = [(INGEST, None), (GEOMETRY, None)]
        for i in range(1, iterations + 1):
            deps += [(PLAN, i), (SYNTHESIZE, i), (LIFT, i)]
        if step == "refine":
            return deps + [(FIT, None)]
        if step == "export" and fit:
            deps.append((FIT, None))
            if refine:
                deps.append((REFINE, None))
        return deps
    if step == "evaluate":
        return [(EXPORT, None)]  # the export's key covers every step before it
    if step == "score":
        return [(EVALUATE, None)]
    raise KeyError(f"unknown step {step!r}")
