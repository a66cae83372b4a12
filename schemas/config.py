"""Run configuration: one pydantic model per pipeline step, with the paper's defaults.

Every number that changes a stored output lives here, so that a step's cache key can be derived from
the part of the config it reads (``RunConfig.step_config``). Defaults follow the NavCrafter paper
(N=3 iterations, K=3 candidates, 81-frame clips at 256x256, DPM-solver 40 steps, CFG 6.5, LoRA weight
0.7); the ``tiny`` preset shrinks sizes for tests and quick looks.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

Backend = Literal["simulation", "onnx"]


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class IngestConfig(_Section):
    """Validation and normalisation of input photos."""

    max_file_bytes: int = Field(64 * 2**20, gt=0, description="Reject files larger than this.")
    max_pixels: int = Field(
        100_000_000, gt=0, description="Reject images with more pixels (decompression-bomb guard)."
    )
    min_side: int = Field(64, gt=0, description="Reject images whose shorter side is smaller.")
    max_side: int = Field(
        1024, gt=0, description="The stored normalised input is downscaled to this longer side."
    )
    alpha_background: tuple[int, int, int] = Field(
        (255, 255, 255), description="Colour that transparent pixels are composited onto."
    )


class SynthesisConfig(_Section):
    """Video synthesis (paper: Wan2.1 DiT sampled with DPM-solver, 81-frame 256x256 clips)."""

    num_frames: int = Field(81, ge=2, description="Frames per synthesized clip (trajectory length).")
    height: int = Field(256, ge=16)
    width: int = Field(256, ge=16)
    steps: int = Field(40, ge=1, description="DPM-solver steps (onnx backend).")
    guidance_scale: float = Field(6.5, description="Classifier-free guidance scale (onnx backend).")
    lora_scale: float = Field(0.7, description="Camera LoRA weight alpha at inference (onnx backend).")
    flow_shift: float | None = Field(
        None, gt=0, description="Shift of the flow-matching sigmas (onnx backend); None: the exported model's own "
        "scheduler setting (its manifest), else 3.0 (Wan2.1's).")
    fps: int = Field(16, ge=1, description="Frame rate of exported videos (Wan2.1 native rate).")
    # Literal[..., None] is Literal[...] | None (PEP 586), spelled so that its values enumerate as one Literal
    plucker_convention: Literal["relative", "ray", "paper", None] = Field(
        None, description="Plücker-ray convention the run expects the camera control to use (onnx backend; "
        "models.camera.cameras.plucker_rays); None: the exported weights' recorded convention. When set, a model "
        "recorded with another convention is refused (re-export the matching weights).")

    offload: bool = Field(
        False, description="onnx backend: hold one graph of the synthesizer at a time (VAE encoder, image encoder, "
        "DiT, VAE decoder in turn; the others released and reloaded when next needed): less GPU memory, a few "
        "session loads per clip; the frames are the same.")
    model: Literal["navcrafter", "fun-camera"] = Field(
        "navcrafter", description="Synthesizer model (onnx backend): 'navcrafter' (NavCrafter's camera control on "
        "Wan2.1 I2V, models/synthesis/camcontrol.py) or 'fun-camera' (VideoX-Fun's Wan2.1-Fun-V1.1-Control-Camera, "
        "models/synthesis/funcamera.py). The exported synthesizer's manifest must hold that model.")

    # added after stores existed: keys the synthesize step only when set (schemas.keys)
    keyed_when_set: ClassVar[dict[str, Any]] = {"flow_shift": None, "plucker_convention": None,
                                                "model": "navcrafter"}


class PlanConfig(_Section):
    """Camera trajectory planning (see ``navcrafter.models.planning.planners``).

    * ``collision_aware``: the paper's Algorithm 1 (candidates in the search space, collision
      detector, visibility score, spherical interpolation, collision optimisation).
    * ``viewcrafter``: the baseline, ViewCrafter's next-best view: the same K candidates in S, its own utility
      (the empty area of the candidate's point-cloud render), spherical interpolation about o, no collision
      handling.
    * ``orbit``: the foundation's simple orbit around the scene centre (no scoring, no obstacles).

    The search space S is the quarter sphere about the scene centre ``o`` (the point on the input optical axis at
    the ``centre_depth_quantile`` of the input view's depth) facing the input camera, at radii relative to ``d0``,
    the input camera's distance to ``o``, so it scales with the scene; ``safe_radius`` is a physical size, in
    scene units.
    """

    strategy: Literal["collision_aware", "viewcrafter", "viewcrafter_nbv", "explorer", "orbit"] = "collision_aware"
    num_candidates: int = Field(3, ge=1, description="K candidate poses per iteration (paper: 3).")
    radius_range: tuple[float, float] = Field(
        (0.6, 1.0), description="Candidate distance from the scene centre o, times d0 (the search space S is "
        "spheres about o; ViewCrafter moves the radius by d_r = -0.2).")
    azimuth_range_deg: tuple[float, float] = Field(
        (-90.0, 90.0), description="Candidate azimuth about o from the direction o -> input camera (positive: right).")
    elevation_range_deg: tuple[float, float] = Field(
        (-30.0, 30.0), description="Candidate elevation from the horizon (with the azimuth default: the quarter "
        "sphere facing the reference view, ViewCrafter's search space).")
    safe_radius: float = Field(
        0.25, gt=0, description="r_safe in scene units (metres for metric geometry): the camera's "
        "safety margin from any surface.")
    follow_error: float = Field(
        0.1, ge=0, description="Expected camera-following error of the video model per unit of path length: along "
        "a path, G demands a clearance of r_safe plus this times the distance travelled (camera-controlled video "
        "models drift by 5-10 % of the path on RealEstate10K: CameraCtrl, CamI2V). 0: r_safe everywhere.")
    anchor_fraction: float = Field(
        0.5, gt=0, le=1, description="m0 of the score F = (1-m) min(1, m/m0), m = seen fraction of the mask.")
    smoothness: float = Field(1.0, ge=0, description="lambda of the collision optimisation's smoothness term.")
    max_resample: int = Field(
        0, ge=0, description="Extra draws of K candidates until K pass G (0: exactly K candidates, the baseline's "
        "budget; a colliding candidate is first pulled towards o until G passes it).")
    unknown_space: Literal["occupied", "free"] = Field(
        "occupied", description="How G treats space no camera has seen: 'occupied' (only seen free space "
        "is allowed) or 'free' (collisions are proximity to the cloud and being behind an observed surface).")
    centre_depth_quantile: float = Field(
        0.5, gt=0, lt=1, description="Scene centre o = point at this depth quantile on the optical axis.")
    orbit_step_deg: float = Field(20.0, gt=0, le=90, description="Azimuth step of the orbit planner.")
    orbit_max_shift: float = Field(
        1.0, gt=0, description="Cap on the camera displacement of one orbit step, in scene units.")
    orbit_radius_scale: float = Field(
        0.85, gt=0, description="Orbit target distance to the centre as a fraction of the initial one.")
    trajectory: list[str] | None = Field(
        None, description="A user's camera path in place of the planner (models/planning/user.py): iteration k takes "
        "entry (k-1) mod len, a preset NAME[:SIZE] (orbit, arc, dolly, pan, tilt, truck, pedestal, spiral, "
        "lookaround; SIZE in the preset's degrees or amount) or a camera file (RealEstate10K .txt, transforms.json, "
        "camera_path.json, camera-to-world matrices .npy/.json). Checked by G; see trajectory_repair.")
    trajectory_extent: float = Field(
        0.5, ge=0, description="A camera file's path is scaled so its farthest camera lies this many times the "
        "current camera's distance to the scene centre from its first; 0 keeps the file's units.")
    trajectory_convention: Literal["opencv", "opengl"] = Field(
        "opencv", description="Camera axes of plain matrix files (.npy, or .json without a 'convention' field).")
    trajectory_repair: bool = Field(
        False, description="Repair a user path that G flags with the collision optimisation (same end poses); "
        "otherwise it is kept with a warning.")

    nbv_step_deg: tuple[float, float] = Field(
        (10.0, 30.0), description="viewcrafter_nbv: ViewCrafter's grid spacings (d_theta, d_phi) in degrees: "
        "candidates at (0, phi), (-theta, phi), (theta/2, phi) from the current pose (ViewCrafter's documented "
        "defaults d_theta 10, d_phi 30).")
    nbv_radius_step: float = Field(
        -0.2, gt=-1, lt=1, description="viewcrafter_nbv: ViewCrafter's d_r: the distance to o is multiplied by "
        "1 + d_r over a clip (ViewCrafter's default -0.2).")
    explore_candidates: int = Field(
        60, ge=3, description="explorer: candidate trajectories scored per iteration (end poses x shapes), for one "
        "clip of synthesis as every planner.")
    explore_voxels: int = Field(48, ge=8, le=160, description="explorer: voxel map cells along its side (3 d0).")
    explore_rays: int = Field(16, ge=4, description="explorer: rays along the longer image side when scoring.")
    explore_frames: int = Field(4, ge=1, description="explorer: frames of a trajectory scored (evenly spaced).")
    explore_accuracy: float = Field(
        0.01, gt=0, description="explorer: the accuracy sought, as a fraction of d0 (a cell seen at range z counts "
        "erf(a d0 / (sqrt2 e z)): the chance its depth lands within a d0).")
    explore_depth_error: float = Field(
        0.03, gt=0, description="explorer: the expected relative depth error of the geometry model (AbsRel 3-5 % of "
        "VGGT / MoGe / DUSt3R, the same sources as the honest simulation).")
    explore_anchor: float = Field(
        0.3, gt=0, le=1, description="explorer: share of each scored frame's rays that should end on known content; "
        "below it the trajectory's score falls linearly.")
    explore_yaw_deg: float = Field(35.0, ge=0, le=90, description="explorer: end poses also turned by +-this.")
    explore_prefix: float = Field(
        0.1, ge=0, le=1, description="explorer: share of the clip's first frames that stay in seen free space.")

    # added after stores existed: keys the plan step only when set (schemas.keys)
    keyed_when_set: ClassVar[dict[str, Any]] = {"trajectory": None, "trajectory_extent": 0.5,
                                                "trajectory_convention": "opencv", "trajectory_repair": False,
                                                "nbv_step_deg": [10.0, 30.0], "nbv_radius_step": -0.2,
                                                "explore_candidates": 60, "explore_voxels": 48, "explore_rays": 16,
                                                "explore_frames": 4, "explore_accuracy": 0.01,
                                                "explore_depth_error": 0.03, "explore_anchor": 0.3,
                                                "explore_yaw_deg": 35.0, "explore_prefix": 0.1}

    @field_validator("trajectory")
    @classmethod
    def _trajectory(cls, value: list[str] | None) -> list[str] | None:
        """Entries checked now (a bad one fails before any work); camera files kept as absolute paths."""
        if value is None:
            return None
        if not value:
            raise ValueError("plan.trajectory must list at least one preset or camera file (or be null)")
        from navcrafter.models.planning.user import parse_spec

        out = []
        for entry in value:
            spec = parse_spec(entry)
            out.append(spec.path if spec.path is not None else spec.text)
        return out

    @model_validator(mode="after")
    def _ranges(self) -> PlanConfig:
        for name in ("radius_range", "azimuth_range_deg", "elevation_range_deg"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"plan.{name} must be (low, high), got ({lo}, {hi})")
        if self.radius_range[0] <= 0:
            raise ValueError("plan.radius_range must be positive")
        if not -90 <= self.elevation_range_deg[0] <= self.elevation_range_deg[1] <= 90:
            raise ValueError("plan.elevation_range_deg must lie within [-90, 90]")
        return self


class LiftConfig(_Section):
    """Lifting synthesized frames to points and fusing them into the scene cloud."""

    max_views: int = Field(12, ge=1, description="Frames of a clip passed to the geometry model.")
    pixel_stride: int = Field(2, ge=1, description="Unproject every n-th pixel in each direction.")
    confidence_threshold: float = Field(0.5, ge=0, le=1)
    voxel_size: float = Field(0.02, gt=0, description="Fusion voxel edge, in scene units (metres).")
    max_depth: float = Field(50.0, gt=0, description="Ignore predicted depth beyond this.")
    icp: bool = Field(True, description=(
        "Refine each lifted view's pose by ICP against the existing cloud (accepted only with enough overlap "
        "and a small correction); the scale always comes from the reference view."))
    icp_distance: float = Field(0.03, gt=0, description=(
        "ICP correspondence distance, relative to the reference view's median depth."))


# The fit's named loss weightings (fit.loss): values of lambda_lpips, lambda_depth, depth_space
LOSS_WEIGHTINGS: dict[str, dict[str, Any]] = {
    "paper": {"lambda_lpips": 1.0, "lambda_depth": 1.0, "depth_space": "inverse"},
    "light": {"lambda_lpips": 0.2, "lambda_depth": 0.1, "depth_space": "median"},
}


class FitConfig(_Section):
    """Geometry-aware 3D Gaussian Splatting fit (``tasks/fit.py``; paper, Sec. III-D).

    Initialised from the final cloud, trained on every synthesized frame at its planned camera except each
    ``holdout_every``-th (held out for PSNR/SSIM/LPIPS) with L1 + ``lambda_lpips`` LPIPS (only with the
    official LPIPS weights; skipped with a note otherwise) + ``lambda_depth`` depth L1 against monocular depth
    calibrated to the lift step's geometry depth, and DropGaussian. Learning rates are 3DGS's; the loss weights are
    the paper's (unit); the size (resolution, iterations, Gaussian budget, and 3DGS's schedule scaled to it) was
    chosen by held-out quality against time on 2 CPU cores (benchmarks/fit_defaults.py,
    models/gaussians/README.md#default-size). On by default. With a GPU, longer fits are cheap: see that README.
    """

    enabled: bool = Field(True, description="Run the fit step after the last lift.")
    iterations: int = Field(500, ge=1, description="Training iterations (one view each).")
    holdout_every: int = Field(8, ge=2, description="Every n-th frame (0, n, 2n, ...) is held out for evaluation.")
    train_stride: int = Field(
        1, ge=1, description="Train on every n-th of the frames not held out (1: all of them). Sparser training "
        "sets are where the depth prior and DropGaussian matter (benchmarks/fitting.py --train-stride).")
    depth_views: Literal["lift", "all"] = Field(
        "all", description="Training frames with depth supervision: 'lift' only those the lift step ran the "
        "geometry model on (calibrated to its depth); 'all' also the others, calibrated to the scene cloud "
        "rendered into the frame (z-buffered points, ``fit.depth_point_size``).")
    depth_point_size: float = Field(
        0.02, gt=0, description="World size of a cloud point when the cloud is rendered as a frame's multi-view "
        "depth (depth_views='all'); the lift voxel size is a good value.")
    resolution: int | None = Field(
        128, ge=8, description="Longer image side for training and evaluation (frames box-downsampled, "
        "intrinsics scaled); None: the synthesis resolution.")
    max_init_points: int | None = Field(
        50_000, ge=1, description="Initialise from at most this many cloud points (a seeded random subset); "
        "None: every point (3DGS).")
    sh_degree: int = Field(3, ge=0, le=3, description="Spherical-harmonics degree (3DGS: 3).")
    sh_degree_interval: int = Field(125, ge=1, description="Iterations per increase of the active SH degree.")
    lr_means: float = Field(1.6e-4, gt=0, description="Position learning rate x scene scale, at the start (3DGS).")
    lr_means_final: float = Field(1.6e-6, gt=0, description="... at the last iteration (log-linear decay).")
    lr_quats: float = Field(1e-3, gt=0)
    lr_scales: float = Field(5e-3, gt=0, description="Learning rate of the log-scales.")
    lr_opacities: float = Field(5e-2, gt=0, description="Learning rate of the opacity logits.")
    lr_sh0: float = Field(2.5e-3, gt=0)
    lr_shN: float = Field(2.5e-3 / 20, gt=0)
    loss: Literal["paper", "light"] = Field(
        "paper", description="Named weighting of the loss; sets lambda_lpips, lambda_depth and depth_space where "
        "they are not given: 'paper' L1 + LPIPS + depth L1 with unit weights, the depth term in inverse depth (the "
        "space the calibration fits); 'light' 1 : 0.2 : 0.1 with the depth term in median-normalised depth (the "
        "earlier default; measured effect in models/gaussians/README.md#the-loss).")
    lambda_lpips: float = Field(1.0, ge=0, description="Weight of the LPIPS term (needs the official weights).")
    lambda_depth: float = Field(1.0, ge=0, description="Weight of the calibrated-depth L1 term.")
    depth_space: Literal["inverse", "median"] = Field(
        "inverse", description="The depth term's space: 'inverse' |1/ED - 1/D| (world units^-1, where the target "
        "is valid, not sky, and the render covers the pixel); 'median' |ED - D| / median(D).")
    drop_gamma: float = Field(0.1, ge=0, lt=1, description="DropGaussian: drop rate r_t = gamma t / T (0: off).")
    depth_confidence: float = Field(
        0.5, ge=0, le=1, description="Geometry pixels at least this confident take part in the depth calibration.")
    densify: bool = Field(True, description="Adaptive density control (clone / split / prune / opacity reset).")
    grow_grad2d: float = Field(2e-4, gt=0, description="Mean screen-space gradient (NDC) that triggers growth.")
    grow_scale3d: float = Field(0.01, gt=0, description="Clone below, split above this size x scene scale.")
    prune_opa: float = Field(0.005, gt=0, lt=0.5, description="Prune Gaussians less opaque than this.")
    prune_scale3d: float = Field(0.1, gt=0, description="Prune Gaussians larger than this x scene scale.")
    densify_start: int = Field(50, ge=0, description="First iteration of density control (gsplat: refine_start_iter).")
    densify_stop: int = Field(375, ge=0, description="Density control stops at this iteration (refine_stop_iter).")
    densify_every: int = Field(25, ge=1, description="Iterations between density-control steps (refine_every).")
    reset_every: int = Field(0, ge=0, description="Opacity reset period (0: never).")
    max_gaussians: int = Field(50_000, ge=1, description="Densification never grows the model beyond this.")
    device: str = Field(
        "auto", pattern=r"^(auto|cpu|cuda(:\d+)?)$", description="Where to train: 'auto' (CUDA when torch sees a "
        "GPU, else the CPU), 'cpu', 'cuda' or 'cuda:N'. Results come back to the CPU either way.")
    renderer: Literal["auto", "cpu", "torch", "gsplat"] = Field(
        "auto", description="Rasterizer: 'auto' (on the CPU navcrafter's compiled kernels; on CUDA gsplat when it "
        "is installed, else the PyTorch renderer), 'cpu', 'torch' (the PyTorch renderer, any device) or 'gsplat' "
        "(CUDA only; `pip install navcrafter[cuda]`). gsplat clamps alpha at 0.999 (ours 0.99) and is not "
        "bit-reproducible; 'cpu' and 'torch' give the same images.")
    threads: int | None = Field(
        None, ge=1, description="Threads of the compiled CPU rasterizer (None: every core; results do not depend "
        "on it).")

    # the density-control fields were called refine_* (gsplat's names) when the first stores were written;
    # cache keys keep those names (schemas.keys), so that renaming them recomputes nothing
    key_names: ClassVar[dict[str, str]] = {"densify_start": "refine_start", "densify_stop": "refine_stop",
                                           "densify_every": "refine_every"}

    @model_validator(mode="before")
    @classmethod
    def _renamed(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("loss") in LOSS_WEIGHTINGS:
            data = {**LOSS_WEIGHTINGS[data["loss"]], **data}
        if isinstance(data, dict):
            for new, old in cls.key_names.items():
                if old in data:
                    raise ValueError(f"fit.{old} was renamed fit.{new} (density control; 'refine' is the refine "
                                     f"step): write fit.{new}")
        return data


class RefineConfig(_Section):
    """Diffusion refinement of rendered views (paper, Sec. III-D; Difix3D+-style), ``tasks/refine.py``.

    After the fit, the Gaussians are rendered at ``views`` novel cameras off the explored trajectory (training
    cameras displaced sideways/up by ``offset`` x the scene scale and turned by up to ``angle_deg``; never the
    held-out cameras), the Refiner role cleans each render (guided by the nearest training frame), and the fit
    goes on for ``iterations`` with the refined views as extra training views (loss weight ``weight``).
    """

    enabled: bool = Field(False, description="Run the refine step after the fit (needs fit.enabled).")
    views: int = Field(8, ge=1, description="Novel views rendered and refined.")
    offset: float = Field(0.08, gt=0, description="Displacement of a novel camera from its training camera, "
                          "x the scene scale (the median camera-to-cloud distance).")
    angle_deg: float = Field(8.0, ge=0, description="Largest turn (yaw and pitch) of a novel camera.")
    iterations: int = Field(1000, ge=1, description="Training iterations after adding the refined views.")
    weight: float = Field(1.0, gt=0, le=1, description="Loss weight of a refined view (real views: 1; the "
                          "paper's recipe uses the refined views as training views, i.e. 1).")
    depth: bool = Field(True, description="Depth term on the refined views too (their monocular depth calibrated "
                        "to the scene cloud rendered there), i.e. the fit's loss; false: colour terms only.")


class EvaluationConfig(_Section):
    """The evaluation suite (``navcrafter evaluate``; ``flows/evaluate.py``)."""

    pose_frames: int = Field(
        14, ge=3, description="Frames of each clip scored (the paper scores 14): with frame_choice 'first' the "
        "pose_frames frames after the conditioning frame (image metrics, FID/FVD; COLMAP for R_err/T_err also gets "
        "the conditioning frame: pose_frames + 1); with 'spaced' pose_frames frames evenly spaced over the clip."
    )
    frame_choice: Literal["first", "spaced"] = Field(
        "first", description="'first': the conditioning frame and the `pose_frames` frames after it, as the paper "
        "scores (image metrics on frames 1..pose_frames, COLMAP on 0..pose_frames); 'spaced': evenly spaced over "
        "the clip (first and last frame included; the same frames for both)."
    )
    lpips_net: Literal["alex", "vgg"] = Field("alex", description="LPIPS backbone.")
    weights_dir: Path | None = Field(
        None, description="Folder with the official evaluation weights (LPIPS, FID Inception, FVD I3D); "
        "default $NAVCRAFTER_EVAL_WEIGHTS or ~/.cache/navcrafter/eval. Missing files make those metrics "
        "'unavailable'."
    )
    camera_guidance: bool = Field(True, description="Run COLMAP on the synthesized clips (R_err/T_err).")


class SimulationConfig(_Section):
    """The simulation backend's stand-ins for the learned models, and how they fail (``models/simulation``).

    ``preset = "honest"`` (default): the simulated roles fail the way real models fail, with every error size
    fixed from published measurements *before* any result was looked at (source beside each field; figures
    recalled from the papers, which could not be re-read from the machine this was built on). ``"perfect"``:
    the old behaviour for unit tests of plumbing: the synthesizer renders the truth exactly at the requested
    poses (also inside objects and in unseen regions) and geometry sees the true cameras plus small jitter;
    the honest-only fields (``drift_*``, ``hallucinate``, ``anchor_*``, ``variant_shift_m``, ``structure_shift_m``,
    ``extent_change``, ``opening_probability``, ``corrupt_*``, ``pose_trans_rel``, ``depth_lowfreq``,
    ``depth_clip_*``, ``refine_observed_only``) are then ignored; the other geometry errors apply in both.

    The geometry prediction is returned like VGGT's: in the first view's camera frame at an unknown
    scale, so the lifting code must recover the scale exactly as with a real model.
    """

    preset: Literal["honest", "perfect"] = Field(
        "honest", description="'honest': the simulated roles drift, hallucinate and break down like real models; "
        "'perfect': truth at the requested poses (unit tests of plumbing only).")
    supersample: int = Field(1, ge=1, le=4, description="Anti-aliasing factor of synthesized frames.")
    drift_rot_deg: float = Field(
        3.0, ge=0, description="Synthesizer: rotation error of the video's camera against the requested one at the "
        "clip's last frame (grows linearly from 0 at frame 0; random axis, half-normal size with this mean). "
        "Source: camera-controlled video models on RealEstate10K, e.g. CameraCtrl (He et al. 2024, Tab. 1, "
        "RotErr ~1.3-1.5 summed over 16 frames, i.e. a few degrees per frame relative to frame 0) and CamI2V "
        "(Zheng et al. 2024, lower); 3 deg at the end of a clip (1.5 deg on average) sits between them.")
    drift_trans: float = Field(
        0.08, ge=0, description="Synthesizer: translation error at the clip's last frame as a fraction of the clip's "
        "path length (random direction, half-normal size with this mean). Source: the TransErr of the same "
        "models (CameraCtrl, CamI2V) is of the order of 5-10 % of the camera path on RealEstate10K.")
    hallucinate: bool = Field(
        True, description="Synthesizer: content the current cloud does not show is re-drawn from a per-clip variant "
        "of the scene (objects moved by up to variant_shift_m, every texture re-drawn): plausible, not the truth, "
        "different from clip to clip. A video model copies what its point-cloud render shows and invents the rest.")
    anchor_tolerance_m: float = Field(
        0.05, gt=0, description="Synthesizer: a pixel shows the truth only where its true surface lies within this "
        "of the current cloud (metres; 2.5 x the default lift voxel).")
    variant_shift_m: float = Field(
        0.3, ge=0, description="Synthesizer: largest horizontal displacement of an object in a clip's variant scene.")
    corrupt_clearance_m: float = Field(
        0.25, ge=0, description="Synthesizer: frames whose true camera is nearer than this to a surface (or inside "
        "one) come out corrupted, fully at contact: what video models make of a close-up blob of points "
        "(ViewCrafter and NavCrafter show such failures; the size is the paper's r_safe).")
    scale_sigma: float = Field(
        0.2, ge=0, description="Geometry: log-sigma of the arbitrary global scale of each call "
        "(the first call's scale becomes the scene's world scale)."
    )
    depth_noise: float = Field(0.004, ge=0, description="Geometry: relative per-pixel depth noise (sigma).")
    depth_lowfreq: float = Field(
        0.01, ge=0, description="Geometry (honest): sigma of a smooth multiplicative depth error per view, on top of "
        "the clip's shared error (depth_clip_bias): the frame-to-frame inconsistency within a clip. Source: "
        "single-view AbsRel of 3-5 % (VGGT, Wang et al. 2025; MoGe-2, Wang et al. 2025, on NYUv2/ETH3D) is "
        "mostly shared across a sequence (the multi-view tables cited at depth_clip_bias); 1 % stays per view.")
    pose_rot_deg: float = Field(
        0.5, ge=0, description="Geometry: rotation error (sigma, degrees) of each predicted pose but the first. "
        "Source: VGGT's relative-rotation accuracy on RealEstate10K/CO3D (AUC@30 85-88, errors of a degree "
        "or less for the small baselines of a video clip).")
    pose_trans: float = Field(
        0.003, ge=0, description="Geometry: absolute translation jitter (sigma) of predicted poses, in metres."
    )
    pose_trans_rel: float = Field(
        0.02, ge=0, description="Geometry (honest): translation error (sigma) as a fraction of the camera's distance "
        "to the first view. Source: VGGT's relative translation-direction accuracy (same tables: ~1 deg, ~2 %).")
    focal_noise: float = Field(0.0, ge=0, description="Geometry: relative error of the predicted focal length.")
    edge_confidence: float = Field(
        0.2, ge=0, le=1, description="Geometry: confidence assigned at depth discontinuities."
    )
    # --- issue 30: fidelity of the honest preset (fixed before any planning result was looked at) ---
    structure_shift_m: tuple[float, float] = Field(
        (0.3, 1.0), description="Synthesizer (honest): unanchored walls, ceilings and facades of a clip's variant "
        "scene move along their normal by this range (metres, random sign). Source: single-image layout "
        "estimation errs by this much on real rooms (e.g. HorizonNet / LED2-Net on ZInD/MatterportLayout: 3D "
        "IoU 80-85 %, i.e. walls 0.3-1 m off in 5-7 m rooms), and a video model draws unseen structure with no "
        "better information than one image.")
    extent_change: tuple[float, float] = Field(
        (0.10, 0.20), description="Synthesizer (honest): a variant room's extent along each horizontal axis changes "
        "by this fraction (random sign; the same layout-error figures as structure_shift_m, as extents).")
    opening_probability: float = Field(
        0.5, ge=0, le=1, description="Synthesizer (honest): probability that a variant room gains a door-sized "
        "opening in a random wall (an unseen wall is as likely to hold a door as not; the procedural scenes hold "
        "no openings to remove).")
    anchor_falloff_m: float = Field(
        0.072, ge=0, description="Synthesizer (honest): soft anchoring: a pixel whose true surface lies d from the "
        "cloud shows the truth with probability exp(-d / this) (a smooth per-frame random field decides, so "
        "unanchored regions come in patches). 0.072 m puts the median at the former hard 5 cm test "
        "(anchor_tolerance_m, 2.5 x the lift voxel); no paper measures this fall-off directly, so the "
        "figure keeps the former median and only adds the fall-off. 0: the hard anchor_tolerance_m test.")
    depth_clip_bias: float = Field(
        0.03, ge=0, description="Geometry (honest): sigma of a smooth multiplicative depth error shared by every frame "
        "of one call (a clip), a field over the ground-truth world (wavelengths 1-4 m), so fusing the clip's "
        "frames does not average it away. Source: per-sequence-aligned depth errors of multi-view models stay "
        "at AbsRel 3-5 % (DUSt3R, Wang et al. 2024, Tab. multi-view depth; VGGT, Wang et al. 2025, Tab. 4 "
        "multi-view depth on DTU/ETH3D; MoGe, Wang et al. 2025, scale-invariant AbsRel 3-6 %).")
    depth_clip_shape: float = Field(
        0.03, ge=0, description="Geometry (honest): sigma of a per-call shape bias b: depth d -> d (1 + b ln(d / "
        "median d)), far content stretched or compressed for the whole clip (the affine / scale-shift "
        "ambiguity the same papers report: their scale-and-shift-aligned AbsRel beats scale-only by 1-2 %).")
    corrupt_near_m: float = Field(
        0.5, ge=0, description="Synthesizer (honest): close-up corruption grows with the fraction of the frame a "
        "surface nearer than this fills (between corrupt_fill's bounds), not with the camera's clearance; "
        "0.5 m is 2 r_safe, the near distance of the close_frames metric. 0: the clearance test "
        "(corrupt_clearance_m).")
    corrupt_fill: tuple[float, float] = Field(
        (0.25, 0.75), description="Synthesizer (honest): near-surface fill fractions at which corruption starts and "
        "is total (a point-cloud render this close is a sparse blob over that share of the frame: ViewCrafter's "
        "and NavCrafter's close-up failures).")
    refine_observed_only: bool = Field(
        True, description="Refiner stand-in (honest): moves a render towards the truth only where the cloud "
        "observed the scene (the same anchoring as the synthesizer); elsewhere towards a variant of the scene. "
        "A diffusion refiner repairs artifacts, it does not know unseen content.")
    refine_strength: float = Field(
        0.7, ge=0, le=1, description="Refiner stand-in: how far a render is moved toward the true view "
        "(refined = render + strength x (truth - render) + noise; 1: a perfect refiner).")
    refine_noise: float = Field(0.02, ge=0, description="Refiner stand-in: sigma of added pixel noise (0-1 range).")

    @property
    def honest(self) -> bool:
        return self.preset == "honest"


class RunConfig(BaseModel):
    """Everything a run needs besides its inputs and its store."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    backend: Backend = Field(
        "simulation",
        description="'simulation' renders procedural ground truth in place of learned models; "
        "'onnx' runs exported models from model_dir.",
    )
    model_dir: Path | None = Field(None, description="Directory of exported ONNX models (onnx backend).")
    iterations: int = Field(3, ge=0, description="N: plan/synthesize/lift iterations (paper: 3).")
    seed: int = Field(0, description="Base seed; each step derives its own from scene, step and config.")
    max_parallel_scenes: int = Field(2, ge=1, description="Scenes processed at once in one process.")
    gpu_limit: str | None = Field(
        None,
        description="Name of a Prefect global concurrency limit (`prefect gcl create NAME --limit GPUs`) "
        "of which each model-running step (geometry, synthesize, lift, fit) occupies one slot; "
        "None: unbounded, and no API call per step.",
    )
    release_models: bool = Field(
        True, description="onnx backend: release a step's models (their onnxruntime sessions) when it ends, so a "
        "process holds one step's models at a time (a 24 GB GPU holds one role at a time; reloading costs seconds "
        "per step); False keeps every loaded role for the process (faster on a large GPU, more memory).")
    ingest: IngestConfig = IngestConfig()
    synthesis: SynthesisConfig = SynthesisConfig()
    plan: PlanConfig = PlanConfig()
    lift: LiftConfig = LiftConfig()
    fit: FitConfig = FitConfig()
    refine: RefineConfig = RefineConfig()
    simulation: SimulationConfig = SimulationConfig()
    evaluation: EvaluationConfig = EvaluationConfig()

    @field_validator("model_dir")
    @classmethod
    def _expand(cls, v: Path | None) -> Path | None:
        return None if v is None else Path(v).expanduser()

    # fields that change no stored output (scheduling only): the only ones that key no step
    # (tests/schemas/test_cache_keys.py checks every other field keys some step)
    NOT_KEYING: ClassVar[dict[str, str]] = {
        "max_parallel_scenes": "how many scenes run at once", "gpu_limit": "which concurrency limit steps wait on",
        "fit.threads": "the compiled rasterizer's threads (its results do not depend on them)",
        "release_models": "when loaded models are freed (outputs do not depend on it)",
        "synthesis.offload": "whether the synthesizer's graphs are held one at a time (the frames do not change)"}

    @model_validator(mode="after")
    def _check(self) -> RunConfig:
        """Every rule between sections, in one place (checked whenever a config is made or loaded)."""
        problems = []
        if self.backend == "onnx" and self.model_dir is None:
            problems.append("backend 'onnx' needs model_dir, a directory of exported ONNX models: pass "
                            "`--models DIR` (or model_dir in the config file); `navcrafter models export-all DIR` "
                            "writes one (random weights), `navcrafter models export-synthesizer/-geometry/"
                            "-monodepth/-refiner` export each model")
        if self.fit.enabled and self.iterations < 1:
            problems.append("fit.enabled needs iterations >= 1: the Gaussians are fitted to the synthesized frames")
        if self.refine.enabled and not self.fit.enabled:
            problems.append("refine.enabled needs fit.enabled: the refine step starts from the fitted Gaussians")
        if problems:
            raise ValueError("; ".join(problems))
        return self

    # -- hashing ---------------------------------------------------------------------------------
    def step_config(self, step: str) -> dict[str, Any]:
        """The part of the config that a step's output depends on (``schemas.keys.step_config``)."""
        from navcrafter.schemas.keys import step_config
        from navcrafter.schemas.layout import STEPS

        if step not in STEPS:
            raise KeyError(f"unknown step {step!r}; known: {sorted(STEPS)}")
        return step_config(STEPS[step], self)

    def config_hash(self) -> str:
        from navcrafter.schemas.keys import stable_hash

        return stable_hash(self.model_dump(mode="json"))

    # -- loading ---------------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path | None = None, preset: str = "paper",
             overrides: dict[str, Any] | None = None) -> RunConfig:
        """Preset, then a YAML/JSON file, then dotted overrides (``{"synthesis.num_frames": 9}``)."""
        data = PRESETS[preset]() if preset in PRESETS else _unknown_preset(preset)
        if path is not None:
            p = Path(path)
            if not p.is_file():
                raise FileNotFoundError(f"config file {p} does not exist")
            loaded = yaml.safe_load(p.read_text()) or {}
            if not isinstance(loaded, dict):
                raise ValueError(f"config file {p} must hold a mapping, got {type(loaded).__name__}")
            data = _deep_merge(data, loaded)
        for dotted, value in (overrides or {}).items():
            data = _deep_merge(data, _dotted_to_nested(dotted, value))
        return cls.model_validate(data)


def _paper() -> dict[str, Any]:
    return {}


def _tiny() -> dict[str, Any]:
    return {
        "iterations": 2,
        "synthesis": {"num_frames": 9, "height": 64, "width": 64},
        "lift": {"max_views": 4, "pixel_stride": 1, "voxel_size": 0.03},
        "fit": {"enabled": False, "iterations": 40, "resolution": 32, "max_init_points": 3000, "sh_degree": 1,
                "sh_degree_interval": 20, "lr_means": 1.6e-3, "lr_means_final": 1.6e-4, "densify_start": 10,
                "densify_every": 10, "densify_stop": 30, "reset_every": 0, "max_gaussians": 4000},
    }


PRESETS = {"paper": _paper, "tiny": _tiny}


def _unknown_preset(name: str) -> dict[str, Any]:
    raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")


def _deep_merge(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    out = dict(a)
    for k, v in b.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _dotted_to_nested(dotted: str, value: Any) -> dict[str, Any]:
    keys = dotted.split(".")
    nested: dict[str, Any] = {keys[-1]: value}
    for k in reversed(keys[:-1]):
        nested = {k: nested}
    return nested
