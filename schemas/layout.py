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

Each step is declared once, here, by its ``StepSpec``: what it writes (arrays, attrs), what it reads
(``reads``: the upstream steps whose keys enter its cache key), which config keys it (``keyed_by``, see
``schemas.keys``), whether it holds a GPU slot (``gpu``), when it runs (``stage``, ``runs_if``), its output
version (``version``); its body (a plain function over a ``tasks.steps.StepContext``) is registered by name in
``tasks/bodies.py``.
Dependencies, cache keys, the order of a scene's steps and the Prefect tasks are derived from these specs
(``schemas.keys``, ``tasks.steps``, ``flows.explore``).
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
class Read:
    """An upstream output a step reads; its key enters the reader's cache key (in declaration order).

    ``step``: a step name, or ``"cloud"`` (the step holding the scene cloud after an iteration: ``geometry``
    after 0, ``lift`` after k). ``at``: ``None`` for a non-iterative step; ``"k"`` / ``"k-1"`` for the reader's
    own / the previous iteration; ``"each"`` for iterations 1..N, the steps of ``also`` interleaved per iteration.
    ``otherwise``: the step read instead when ``at`` falls on iteration 0. ``if_runs``: read only when that
    step runs in this config (``StepSpec.runs_if``)."""

    step: str
    at: str | None = None
    otherwise: str | None = None
    also: tuple[str, ...] = ()
    if_runs: str | None = None


@dataclass(frozen=True)
class Key:
    """One entry of a step's cache-key config (``schemas.keys.step_config``): ``name`` -> the value at the
    dotted config ``path`` (a tuple of paths: the list of their values). A whole section is dumped as JSON
    (``include``: only these fields; ``drop_prefix``: without the fields starting with it). ``simulation_only``:
    the entry is ``None`` unless the backend is the simulation; ``if_true``: present (as ``True``) only when the
    value is true."""

    name: str
    path: str | tuple[str, ...]
    include: tuple[str, ...] | None = None
    drop_prefix: str | None = None
    simulation_only: bool = False
    if_true: bool = False


@dataclass(frozen=True)
class StepSpec:
    name: str
    path: str  # may contain "{k}"
    doc: str
    arrays: tuple[ArraySpec, ...] = ()
    attrs: tuple[str, ...] = ()
    iterative: bool = False
    extra: dict[str, str] = field(default_factory=dict)
    # -- how the step runs (derived from these: dependencies, cache keys, order, Prefect tasks) -------------
    reads: tuple[Read, ...] = ()
    keyed_by: tuple[Key, ...] = ()
    # model roles whose exported versions key the step (onnx backend), with backend, model_dir and seed;
    # None: the step is keyed by none of them
    models: tuple[str, ...] | None = None
    gpu: bool = False  # holds a slot of the ``gpu_limit`` concurrency limit while it runs
    stage: str = "scene"  # "ingest" (per file), "scene" (a scene run, in order), "report" (after a scene run)
    runs_if: str | None = None  # a dotted boolean config field: the step runs only when it is true
    version: int = 1  # bump when the outputs change meaning; versions > 1 enter the key (as "outputs")

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


MODEL_ROLES = ("synthesizer", "geometry", "monodepth")  # the roles a scene's models come from (onnx backend)
_SIM = Key("simulation", "simulation", drop_prefix="refine_", simulation_only=True)  # refiner stand-in: refine only
_LPIPS = Key("lpips", "evaluation", include=("lpips_net", "weights_dir"))
_EACH_ITERATION = Read("plan", at="each", also=("synthesize", "lift"))

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
    stage="ingest",
    keyed_by=(Key("ingest", "ingest"), Key("resolution", ("synthesis.height", "synthesis.width"))),
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
    gpu=True, models=MODEL_ROLES,
    reads=(Read("ingest"),),
    # the first cloud is filtered and fused like the lifts' clouds
    keyed_by=(_SIM, Key("lift", "lift", include=("pixel_stride", "confidence_threshold", "voxel_size", "max_depth"))),
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
    # version 2: the search space is the quarter sphere about o, and iteration k starts at the estimated last camera
    models=MODEL_ROLES, version=2,
    reads=(Read("cloud", at="k-1"), Read("plan", at="k-1", otherwise="geometry")),
    keyed_by=(Key("plan", "plan"), Key("frames", ("synthesis.num_frames", "synthesis.height", "synthesis.width")),
              Key("point_size", "lift.voxel_size")),
)

SYNTHESIZE = StepSpec(
    "synthesize", "iter_{k}/synthesize",
    "The video clip synthesized along the trajectory of iteration k, conditioned on the view at its first camera "
    "(the working image, then the last frame of clip k-1) with the input photo as an extra reference from k = 2.",
    arrays=(ArraySpec("frames", "uint8", ("T", "H", "W", 3), (1, "H", "W", 3), "RGB frames"),
            # the simulation's hidden truth of the clip, never read by a step that stands for a real model's
            # input (only the simulated roles and the ground-truth metrics read it)
            ArraySpec("true_c2w", "float64", ("T", 4, 4), ("T", 4, 4), "simulation only: world c2w at which each "
                      "frame was really taken (the requested path plus the video model's drift)", optional=True),
            ArraySpec("true_depth", "float32", ("T", "H", "W"), (1, "H", "W"), "simulation only: z-depth (world "
                      "units) of what each frame shows, hallucinated content included; 0 = sky", optional=True),
            ArraySpec("true_quality", "float32", ("T",), ("T",), "simulation only: per frame, the fraction of "
                      "pixels that show the true scene (1) rather than hallucinated or corrupted content",
                      optional=True)),
    iterative=True,
    gpu=True, models=MODEL_ROLES,
    # the conditioning image: the last frame of clip k-1, for k = 1 the working image (ingest); the reference
    # camera: the input pose (geometry)
    reads=(Read("ingest"), Read("plan", at="k"), Read("cloud", at="k-1"),
           Read("synthesize", at="k-1", otherwise="ingest"), Read("geometry")),
    keyed_by=(Key("synthesis", "synthesis"), _SIM),
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
    gpu=True, models=MODEL_ROLES, version=2,  # 2: a bit-reproducible ICP of our own
    reads=(Read("ingest"), Read("geometry"), Read("plan", at="k"), Read("synthesize", at="k"), Read("cloud", at="k-1")),
    keyed_by=(Key("lift", "lift"), _SIM),
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
           "lpips", "lpips_note", "init_psnr", "scene_scale", "train_seconds", "final_loss", "peak_rss_mb"),
    # version 2: the compiled CPU rasterizer under renderer 'auto', the paper's loss, peak memory in attrs
    gpu=True, models=MODEL_ROLES, runs_if="fit.enabled", version=2,
    reads=(Read("ingest"), Read("geometry"), _EACH_ITERATION),
    keyed_by=(Key("fit", "fit"), _SIM, _LPIPS),
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
           "train_seconds", "peak_rss_mb"),
    # version 2: the fit's loss on the refined views (weight 1, depth)
    gpu=True, models=(*MODEL_ROLES, "refiner"), runs_if="refine.enabled", version=2,
    reads=(Read("ingest"), Read("geometry"), _EACH_ITERATION, Read("fit")),
    keyed_by=(Key("refine", "refine"), Key("simulation", "simulation", simulation_only=True),
              Key("fit", "fit", include=("device", "renderer", "lr_means_final", "lr_quats", "lr_scales",
                                         "lr_opacities", "lr_sh0", "lr_shN", "lambda_depth", "drop_gamma",
                                         "sh_degree", "lambda_lpips", "depth_space", "depth_point_size")),
              _LPIPS),
)

EXPORT = StepSpec(
    "export", "exports",
    "User-facing files, stored beside the group's zarr.json; attrs list them with checksums.",
    attrs=("files",),

    reads=(Read("ingest"), Read("geometry"), _EACH_ITERATION, Read("fit", if_runs="fit"),
           Read("refine", if_runs="refine")),
    keyed_by=(Key("fps", "synthesis.fps"), Key("iterations", "iterations"), Key("fit", "fit.enabled", if_true=True),
              Key("refine", "refine.enabled", if_true=True)),
)

EVALUATE = StepSpec(
    "evaluate", "evaluation",
    "Scene metrics (tasks/scene_metrics.py), kept so that a rerun does not recompute them; also appended "
    "to the metrics table.",
    attrs=("metrics", "iterations"),
    # version 2: attrs record the iterations; 3: true-path, per-iteration and close-frame metrics
    stage="report", version=3,
    reads=(Read("export"),),  # the export's key covers every step before it
    keyed_by=(Key("backend", "backend"), Key("plan", "plan"), Key("iterations", "iterations")),
)

SCORE = StepSpec(
    "score", "scores",
    "One scene's rows of the evaluation suite (navcrafter evaluate): image metrics, camera guidance "
    "(COLMAP), runtime, geometry; rows in the schema of the evaluations table, kept in attrs.",
    attrs=("rows",),
    stage="suite",
    reads=(Read("evaluate"),),
    keyed_by=(Key("backend", "backend"), Key("evaluation", "evaluation")),
)

STEPS: dict[str, StepSpec] = {s.name: s for s in (INGEST, GEOMETRY, PLAN, SYNTHESIZE, LIFT, FIT, REFINE, EXPORT,
                                                  EVALUATE, SCORE)}


def scene_group(scene_id: str) -> str:
    return f"scenes/{scene_id}"


def cloud_step(k: int) -> tuple[StepSpec, int | None]:
    """Which step holds the scene cloud after iteration ``k``."""
    return (GEOMETRY, None) if k == 0 else (LIFT, k)


def scene_steps_in_order() -> tuple[StepSpec, ...]:
    """The steps of a scene run in declaration order (each iterative run of steps repeats per iteration)."""
    return tuple(s for s in STEPS.values() if s.stage == "scene")
