"""Settings of the simulation backend (composed into the run config by schemas/config.py)."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import Field

from navcrafter.models.settings import Section as _Section


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
    common_random_numbers: bool = Field(
        False, description="Every step's random seed from the run's base seed, the scene, the step and the iteration "
        "(tasks/steps.py step_seed) instead of from its cache key, so two runs of one scene that differ in a setting "
        "meet the same simulated errors at the same iteration (clip drift, hallucinated variant, geometry noise, "
        "refiner stand-in; the planner's own draws too): paired comparisons of planner variants without the "
        "simulation's redraw noise. The cache key still holds every setting; only the seed's source changes. "
        "False: seeds from the keys (every setting, even one nothing reads, redraws the simulation).")

    # added after stores existed: keys its steps only when set (schemas.keys), so default stores and seeds stay
    keyed_when_set: ClassVar[dict[str, Any]] = {"common_random_numbers": False}

    @property
    def honest(self) -> bool:
        return self.preset == "honest"
