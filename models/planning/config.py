"""Settings of camera trajectory planning (composed into the run config by schemas/config.py)."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import Field, field_validator, model_validator

from navcrafter.models.planning.user import parse_spec
from navcrafter.models.settings import Section as _Section


class PlanConfig(_Section):
    """Camera trajectory planning (see ``navcrafter.models.planning.planners``).

    * ``explorer`` (default): the safe explorer of issue 30 (``navcrafter.models.planning.explore``): information
      gain over a voxel map summed over many candidate trajectories, optimistic-but-safe unknown space; it sees more
      than Algorithm 1 at a tenth of its planning time (models/planning/README.md).
    * ``collision_aware``: the paper's Algorithm 1 (candidates in the search space, collision
      detector, visibility score, spherical interpolation, collision optimisation).
    * ``viewcrafter_nbv``: ViewCrafter's next-best view from the current pose, as its code does it.
    * ``viewcrafter``: the baseline, ViewCrafter's next-best view: the same K candidates in S, its own utility
      (the empty area of the candidate's point-cloud render), spherical interpolation about o, no collision
      handling.
    * ``orbit``: the foundation's simple orbit around the scene centre (no scoring, no obstacles).

    The search space S is the quarter sphere about the scene centre ``o`` (the point on the input optical axis at
    the ``centre_depth_quantile`` of the input view's depth) facing the input camera, at radii relative to ``d0``,
    the input camera's distance to ``o``, so it scales with the scene; ``safe_radius`` is a physical size, in
    scene units.
    """

    strategy: Literal["collision_aware", "viewcrafter", "viewcrafter_nbv", "explorer", "orbit"] = "explorer"
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
    explore_yaw_turns: int = Field(
        1, ge=1, le=4, description="explorer: end poses turned by +-k x explore_yaw_deg for k = 1 .. this (1: "
        "+-explore_yaw_deg only; 2 adds +-2 x explore_yaw_deg, a turn that looks past the side of the input view).")
    explore_prefix: float = Field(
        0.1, ge=0, le=1, description="explorer: share of the clip's first frames that stay in seen free space.")
    explore_reach: float = Field(
        1.0, ge=0, description="explorer: how far (voxel-map cells) a frame may stand beyond the seen free space, in "
        "unknown space an earlier frame of its clip looked at (0: only seen free space).")
    explore_ball: float = Field(
        0.5, ge=0, le=1, description="explorer: a frame admitted in unknown space (looked at by an earlier frame of "
        "its clip, not seen free) must also have its clearance ball seen: probes at 0.5 and 1 x this x the clearance "
        "G demands there (r_safe + the follow error along the path), in 26 directions, each seen free by an earlier "
        "view or looked at by an earlier frame of the clip with nothing observed in the way; otherwise the frame is "
        "refused (the path is then shortened or another taken). 0: off, the explorer before it (development room 0 "
        "with explore_accuracy 0.03 met a ceiling 0.30 m above a dolly's end that no frame looked at; "
        "benchmarks/results/planning-explore10-dev). 0.5 with explore_ball_up, explore_ball_seen_free and without "
        "explore_ball_open_sky: the default since collide15 (the one setting with 0 collisions on every development "
        "draw, collide14; models/planning/README.md).")
    explore_ball_follow_error: float | None = Field(
        None, ge=0, description="explorer: the follow error the clearance ball of explore_ball grows with along the "
        "path: its radius is explore_ball x (r_safe + this x the distance travelled). None: G's follow error "
        "(explore_follow_error, the drift's 99 % quantile; the rule of explore11); 0.07: about the simulated "
        "drift's median (a half-normal of mean drift_trans 0.08 has median 0.068), a ball that never shrinks "
        "below r_safe and grows a quarter as fast (explore12).")
    explore_ball_up: bool = Field(
        True, description="explorer: the clearance ball of explore_ball probed only above the frame (the 9 of its 26 "
        "directions that rise from the ground plane by more than 30 deg); the space beside and below it is not asked "
        "for (the default since collide15). False: every direction (explore11). Why: development room 2 of CRN base "
        "seed 1 (collide13): the default's clip 3 ended 0.53 m below a ceiling no frame had seen, admitted in unknown "
        "space; the full ball costs streets seen.")
    explore_ball_seen_free: bool = Field(
        True, description="explorer: the clearance ball of explore_ball asked at every frame past the prefix, those in "
        "seen free space too (the default since collide15); False: only at frames admitted in unknown space "
        "(explore11). Why: development room 7 of CRN base seed 4 (collide14): the default's dolly met a ceiling no "
        "view had shown at frames seen free (the position in view, the space above it not).")
    explore_ball_open_sky: bool = Field(
        False, description="explorer: whether the clearance ball of explore_ball is asked in a scene whose input photo "
        "shows sky (at least explore.SKY_SHARE of its pixels without depth: the geometry found no surface on their "
        "rays). False (the default since collide15): not there (the ball is a ceiling's test: under open sky the space "
        "above a camera looking level is in no view though nothing caps it, and the ball refused street clips for it: "
        "collide13, streets seen -0.066 +- 0.023 with explore_ball 0.5 + explore_ball_up; the rooms' collisions it "
        "removed were under ceilings). True: everywhere (explore11).")
    explore_free_space: Literal["anchored", "all", "share"] = Field(
        "share", description="explorer: which pixels of a generated (lifted) frame carve free space: 'anchored' "
        "(only those whose depth agrees with the cloud the clip was conditioned on: copied content; what the video "
        "model invented may hide an object it drew elsewhere or not at all), 'share' (the anchored pixels, and every "
        "pixel with a depth of a frame at least explore_invented_share of whose pixels are anchored; a frame's empty "
        "pixels stay unknown; the default, with explore_invented_share 0 and explore_follow_error 0.15: the decision "
        "was taken on development numbers only, benchmarks/results/planning-explore7-dev) "
        "or 'all' (every pixel, as the input photo's, its empty pixels opened as sky too).")
    explore_invented_share: float = Field(
        0.0, ge=0, le=1, description="explorer, explore_free_space 'share': the anchored share of a generated frame "
        "from which its invented pixels carve free space too (0: every generated frame carves with every pixel that "
        "has a depth; development seeds 0-9: 0 with explore_follow_error 0.15 saw more than 0.3, 0.4 and 0.5 in "
        "rooms and table-tops, benchmarks/results/planning-explore7-dev).")
    explore_follow_error: float | None = Field(
        0.26, ge=0, description="explorer: the follow error its G allows per unit of path (None: plan.follow_error). "
        "0.26 is the 99 % quantile of the simulated drift in the worst direction (simulation.drift_trans 0.08 times "
        "sqrt(pi/2) |N(0,1)| of the path: 0.08 sqrt(pi/2) x 2.576 = 0.258), fixed from that distribution before any "
        "run; 0.15 (the default before, with explore_free_space 'share') let clips that drifted 18-26 % of their path "
        "(development rooms 2 and 3, held-out street-51) collide; models/planning/README.md, "
        "benchmarks/results/planning-explore9-dev).")
    explore_sky: Literal["free", "unknown"] = Field(
        "free", description="explorer: what the input photo's pixels of no depth (sky: the geometry found no "
        "surface on their ray) tell: 'free' (free space without end along the ray) or 'unknown'.")
    explore_anchor_tolerance: float = Field(
        0.08, gt=0, description="explorer: relative depth agreement for a generated pixel to count as anchored (the "
        "geometry model's per-clip depth error of 3-5 %, VGGT / MoGe / DUSt3R, plus the cloud's voxel size).")
    explore_anchor_falloff: float = Field(
        0.0, ge=0, description="explorer: expected anchoring of unknown content, as a length in d0: an unknown cell "
        "counts exp(-max(0, s - cell) / (this x d0)), s its distance to the nearest occupied cell, since a video "
        "model copies what its cloud shows and invents the rest (0: every unknown cell counts fully).")
    explore_revisit: float = Field(
        1.0, ge=0, description="explorer: weight of the accuracy gained on known content: an occupied cell seen "
        "nearer than before counts this x (erf at the new range - erf at the nearest earlier one) (0: off, the "
        "explorer before it; development seeds 0-5, 18 scenes: cov 5 cm +0.016 (11/18 scenes), 2 and 4 did not help on "
        "seeds 0-2; benchmarks/results/planning-explore5-dev).")

    # added after stores existed: keys the plan step only when set (schemas.keys)
    keyed_when_set: ClassVar[dict[str, Any]] = {"trajectory": None, "trajectory_extent": 0.5,
                                                "trajectory_convention": "opencv", "trajectory_repair": False,
                                                "nbv_step_deg": [10.0, 30.0], "nbv_radius_step": -0.2,
                                                "explore_candidates": 60, "explore_voxels": 48, "explore_rays": 16,
                                                "explore_frames": 4, "explore_accuracy": 0.01,
                                                "explore_depth_error": 0.03, "explore_anchor": 0.3,
                                                "explore_yaw_deg": 35.0, "explore_yaw_turns": 1,
                                                "explore_prefix": 0.1,
                                                "explore_free_space": "anchored", "explore_anchor_tolerance": 0.08,
                                                "explore_invented_share": 0.0, "explore_follow_error": None,
                                                "explore_reach": 1.0, "explore_sky": "free", "explore_ball": 0.0,
                                                "explore_ball_follow_error": None, "explore_ball_up": False,
                                                "explore_ball_open_sky": True,
                                                "explore_ball_seen_free": False,
                                                "explore_anchor_falloff": 0.0, "explore_revisit": 0.0}

    @field_validator("trajectory")
    @classmethod
    def _trajectory(cls, value: list[str] | None) -> list[str] | None:
        """Entries checked now (a bad one fails before any work); camera files kept as absolute paths."""
        if value is None:
            return None
        if not value:
            raise ValueError("plan.trajectory must list at least one preset or camera file (or be null)")
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
