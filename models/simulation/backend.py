"""The simulation backend: ground-truth renders standing in for the learned models.

It exists so that the whole product runs, and is measured against ground truth, where no model
weights are present. Everything it produces is labelled ``backend: simulation``.

Two presets (``simulation.preset``, ``schemas.config.SimulationConfig``):

``honest`` (default): the roles fail the way real models fail, so that what the paper's methods exist to fix
is there to be fixed (error sizes from published measurements, cited in the config):

* **Synthesizer** (``simulate``): frame 0 is the conditioning image itself (as Wan I2V reproduces it). The video
  follows the requested motion *relative to where its conditioning image was really taken* (``ClipStart``), with
  a drift growing over the clip (``drift_rot_deg``, ``drift_trans``). Content the current cloud does not show
  is hallucinated: pixels whose true surface is farther than ``anchor_tolerance_m`` from the cloud come from a
  per-clip variant of the scene (objects moved, textures re-drawn: ``variant_scene``). Frames whose true camera
  is within ``corrupt_clearance_m`` of a surface (or inside an object) are corrupted: smeared towards a blob,
  their depth distorted. It returns, besides the frames, their hidden truth (``SimulatedClip``: true cameras,
  the depth of what each frame shows, the fraction of true pixels), which the synthesize step stores for the
  simulated roles and the ground-truth metrics only.
* **Geometry** estimates from the frames: the true cameras of the frames (``hint_c2w``, the stored truth, never
  the request) and the depth of what they show (``hint_depth``), corrupted like a feed-forward model's output:
  an arbitrary global scale per call, a smooth per-view depth error and per-pixel noise, rotation and
  translation errors (absolute and relative to the distance from the first view), optional focal error, low
  confidence at depth discontinuities, nothing on the sky. Results are in the first view's frame
  (``c2w[0] = I``), as VGGT returns them.

``perfect``: the synthesizer renders the true scene exactly at the requested poses (a perfect video model, also
inside objects), and geometry returns the true depth and cameras with the scale, depth noise and pose jitter only.

In both:

* **MonoDepth** returns affine-invariant inverse depth (unknown scale and shift) and the sky mask.
* **Refiner** moves a render of the fitted Gaussians a fraction ``refine_strength`` of the way to the true
  view at that camera and adds pixel noise (``refine_noise``): a diffusion refiner that repairs most, not
  all, of the artifacts. It measures the refine step's plumbing and what a good refiner can give, not
  Difix itself.

Frames of reference: the scene's *world* is the input camera's OpenCV frame at the scale of the
first geometry call (``world_scale`` = that call's scale relative to metres). ``SimulationTruth``
maps between world and the generator's ground-truth frame (z-up, metres).
"""

from __future__ import annotations

import functools
import threading
import zlib
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from navcrafter.models.camera.cameras import Intrinsics, axis_angle_to_matrix, invert_pose, unproject_depth
from navcrafter.models.roles import (
    Backend,
    GeometryPrediction,
    MonoDepthPrediction,
    SynthesisRequest,
)
from navcrafter.models.simulation.config import SimulationConfig
from navcrafter.models.simulation.render import render, render_many
from navcrafter.models.simulation.scenes import GENERATOR_VERSION, KINDS, SceneObject, SimScene, generate_scene
from navcrafter.models.simulation.textures import Material
from navcrafter.models.simulation.worlds.patches import variant_world
from navcrafter.models.simulation.worlds.scene import scene_from_record

BACKEND = "simulation"


class SimulationError(RuntimeError):
    """The simulation backend cannot serve this input (e.g. a real photo without ground truth)."""


@functools.lru_cache(maxsize=4)
def cached_scene(kind: str, seed: int) -> SimScene:
    return generate_scene(kind, seed)


@dataclass
class SimulationTruth:
    """Hidden ground truth of one scene, as recorded by ingest (and the first geometry call)."""

    scene: SimScene
    photo_c2w: np.ndarray  # input camera, ground-truth frame
    work_intrinsics: Intrinsics  # true intrinsics of the working image
    world_scale: float | None = None  # world units per metre; known after the first geometry call

    @classmethod
    def from_record(cls, record: dict, world_scale: float | None = None) -> SimulationTruth:
        spec = record["scene"]
        if spec.get("kind") == "scan":  # a world from a real scan (models/simulation/worlds)
            return cls(scene_from_record(record), np.asarray(record["photo_c2w"], dtype=np.float64),
                       Intrinsics.from_dict(record["work_intrinsics"]), world_scale)
        if int(spec.get("generator_version", -1)) != GENERATOR_VERSION:
            raise SimulationError(
                f"ground truth was made by scene generator v{spec.get('generator_version')}, this is "
                f"v{GENERATOR_VERSION}; regenerate the demo data with `navcrafter demo-data`")
        return cls(cached_scene(spec["kind"], int(spec["seed"])), np.asarray(record["photo_c2w"], dtype=np.float64),
                   Intrinsics.from_dict(record["work_intrinsics"]), world_scale)

    def _scale(self) -> float:
        if self.world_scale is None:
            raise SimulationError("the scene's world scale is unknown: run the initial geometry step first")
        return self.world_scale

    def gt_pose(self, c2w_world: np.ndarray) -> np.ndarray:
        """World camera pose(s) ``[..., 4, 4]`` to the ground-truth frame."""
        w = self._scale()
        out = np.array(c2w_world, dtype=np.float64, copy=True)
        R_in, t_in = self.photo_c2w[:3, :3], self.photo_c2w[:3, 3]
        out[..., :3, :3] = R_in @ out[..., :3, :3]
        out[..., :3, 3] = (out[..., :3, 3] / w) @ R_in.T + t_in
        return out

    def gt_pose_or_photo(self, c2w_world: np.ndarray) -> np.ndarray:
        """Like ``gt_pose``, but also serves the input camera alone before the world scale is known
        (the first geometry call defines the world)."""
        if self.world_scale is None:
            if len(c2w_world) != 1 or not np.allclose(c2w_world[0], np.eye(4)):
                raise SimulationError("the scene's world scale is unknown: run the initial geometry step first")
            return self.photo_c2w[None].copy()
        return self.gt_pose(c2w_world)

    def gt_points(self, points_world: np.ndarray) -> np.ndarray:
        w = self._scale()
        return (np.asarray(points_world, dtype=np.float64) / w) @ self.photo_c2w[:3, :3].T + self.photo_c2w[:3, 3]

    def world_points(self, points_gt: np.ndarray) -> np.ndarray:
        w = self._scale()
        return w * ((np.asarray(points_gt, dtype=np.float64) - self.photo_c2w[:3, 3]) @ self.photo_c2w[:3, :3])

    def intrinsics_for(self, height: int, width: int) -> Intrinsics:
        K = self.work_intrinsics
        return K if (K.height, K.width) == (height, width) else K.resize(width, height)


def _rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(seed & 0xFFFFFFFFFFFFFFFF)


def _require_hint(hint_c2w: np.ndarray | None, n: int) -> np.ndarray:
    if hint_c2w is None:
        raise SimulationError("the simulation backend needs the requested camera poses (hint_c2w)")
    hint = np.asarray(hint_c2w, dtype=np.float64).reshape(-1, 4, 4)
    if len(hint) != n:
        raise ValueError(f"hint_c2w has {len(hint)} poses for {n} frames")
    return hint


class _SimulationRole:
    backend = BACKEND

    def __init__(self, truth: SimulationTruth, config: SimulationConfig) -> None:
        self.truth, self.config = truth, config


@dataclass(frozen=True)
class ClipStart:
    """Hidden truth of a clip's conditioning image: the world c2w where it was really taken, the depth (world
    units, 0 = sky) of what it shows (None: the true scene's), and its fraction of true pixels."""

    c2w: np.ndarray
    depth: np.ndarray | None = None
    quality: float = 1.0


@dataclass
class SimulatedClip:
    """A simulated clip and its hidden truth (world frame and units)."""

    frames: np.ndarray  # [T, H, W, 3] uint8
    true_c2w: np.ndarray  # [T, 4, 4] where each frame was really taken
    true_depth: np.ndarray  # [T, H, W] float32 z-depth of what each frame shows; 0 = sky
    true_quality: np.ndarray  # [T] float32 fraction of pixels showing the true scene


STRUCTURAL = ("floor", "ceiling", "wall_", "ground", "sidewalk", "building", "rug", "picture")


def _structural(name: str) -> bool:
    return any(name.startswith(p) for p in STRUCTURAL)


VariantBuilder = Callable[[SimScene, np.random.Generator, SimulationConfig], SimScene]


def _scan_variant(scene: SimScene, rng: np.random.Generator, cfg: SimulationConfig) -> SimScene:
    """A world from a scan: its object patches moved, its walls and ceiling moved with the generated rooms' settings
    and every patch re-coloured (``worlds.patches``)."""
    return variant_world(scene, int(rng.integers(1 << 31)), cfg.variant_shift_m,
                         structure_shift_m=tuple(cfg.structure_shift_m), extent_change=tuple(cfg.extent_change))


# scene kind -> the builder of its per-clip variants; kinds not listed use ``procedural_variant``. Scanned worlds'
# variants move surface patches (worlds.segments / worlds.patches); other worlds register theirs with
# ``register_variant_builder``.
VARIANT_BUILDERS: dict[str, VariantBuilder] = {"scan": _scan_variant}
_VARIANTS: OrderedDict = OrderedDict()
_VARIANTS_LOCK = threading.Lock()


def register_variant_builder(kind: str, builder: VariantBuilder) -> None:
    """Make ``builder(scene, rng, config)`` draw the per-clip variants of scenes of ``kind``."""
    VARIANT_BUILDERS[kind] = builder


def variant_of(scene: SimScene, variant: int, config: SimulationConfig) -> SimScene:
    """Variant number ``variant`` of ``scene``: what a video model draws where it has nothing to copy (the builder
    registered for ``scene.kind``, else ``procedural_variant``); the last few are cached."""
    fields = ("variant_shift_m", "structure_shift_m", "extent_change", "opening_probability")
    key = (scene.kind, scene.seed, id(scene), int(variant), tuple(getattr(config, f) for f in fields))
    with _VARIANTS_LOCK:
        if key in _VARIANTS:
            _VARIANTS.move_to_end(key)
            return _VARIANTS[key]
    salt = KINDS.index(scene.kind) if scene.kind in KINDS else zlib.crc32(scene.kind.encode())
    rng = np.random.default_rng([int(scene.seed), salt, int(variant), 17])
    out = VARIANT_BUILDERS.get(scene.kind, procedural_variant)(scene, rng, config)
    with _VARIANTS_LOCK:
        _VARIANTS[key] = out
        while len(_VARIANTS) > 6:
            _VARIANTS.popitem(last=False)
    return out


def variant_scene(kind: str, seed: int, variant: int, config: SimulationConfig) -> SimScene:
    """``variant_of`` the procedural scene ``(kind, seed)``."""
    return variant_of(cached_scene(kind, seed), variant, config)


def _bounds(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(mesh.get_min_bound()), np.asarray(mesh.get_max_bound())


def _signed(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(rng.uniform(*lo_hi) * (1 if rng.random() < 0.5 else -1))


def _structure_moves(objs: list[SceneObject], rng: np.random.Generator, cfg: SimulationConfig) -> dict[int, np.ndarray]:
    """Translations of the structural objects of a variant (ground-truth frame, z up): a room's walls move so each
    horizontal extent changes by ``extent_change`` (split at random between its two walls) and its ceiling by the
    same fraction of the height; pictures move with their wall; a street's facades (buildings) move along their
    normal by ``structure_shift_m``. Floors, ground, sidewalks and rugs stay: they carry the camera."""
    moves: dict[int, np.ndarray] = {}
    names = [o.name for o in objs]
    floor = next((i for i, n in enumerate(names) if n == "floor"), None)
    if floor is not None and cfg.extent_change[1] > 0:
        lo, hi = _bounds(objs[floor].mesh)
        height = max((_bounds(o.mesh)[0][2] for o in objs if o.name == "ceiling"), default=2.8)
        for axis, (neg, pos) in ((0, ("wall_west", "wall_east")), (1, ("wall_south", "wall_north"))):
            change = _signed(rng, cfg.extent_change) * float(hi[axis] - lo[axis])
            a = float(rng.random())
            for name, d in ((pos, a * change), (neg, -(1 - a) * change)):
                for i, n in enumerate(names):
                    if n == name:
                        moves[i] = np.eye(3)[axis] * d
        dz = _signed(rng, cfg.extent_change) * height
        for i, n in enumerate(names):
            if n == "ceiling":
                moves[i] = np.array([0.0, 0.0, dz])
        walls = [i for i in moves if names[i].startswith("wall_")]
        for i, n in enumerate(names):
            if n == "picture" and walls:  # hangs on the wall nearest to it
                c = np.mean(_bounds(objs[i].mesh), axis=0)
                gap = [np.abs(np.mean(_bounds(objs[w].mesh), axis=0) - c)[np.flatnonzero(moves[w])[0]]
                       for w in walls]
                moves[i] = moves[walls[int(np.argmin(gap))]]
    if cfg.structure_shift_m[1] > 0:
        for i, n in enumerate(names):
            if n.startswith("building"):
                axis = 0 if n == "building_end" else 1
                moves[i] = np.eye(3)[axis] * _signed(rng, cfg.structure_shift_m)
    return moves


def _with_opening(mesh: o3d.geometry.TriangleMesh, rng: np.random.Generator, width: float = 0.9,
                  height: float = 2.1) -> list[o3d.geometry.TriangleMesh]:
    """A wall box split into the boxes around a door-sized opening at a random place along it (z up)."""
    lo, hi = _bounds(mesh)
    size = hi - lo
    along = 0 if size[0] >= size[1] else 1
    if size[along] < width + 0.4 or size[2] < height + 0.1:
        return [mesh]
    a0 = float(rng.uniform(lo[along] + 0.2, hi[along] - 0.2 - width))
    pieces = []
    for a_lo, a_hi, z_lo, z_hi in ((lo[along], a0, lo[2], hi[2]), (a0 + width, hi[along], lo[2], hi[2]),
                                   (a0, a0 + width, lo[2] + height, hi[2])):
        b_lo, b_hi = lo.copy(), hi.copy()
        b_lo[along], b_hi[along], b_lo[2], b_hi[2] = a_lo, a_hi, z_lo, z_hi
        box = o3d.geometry.TriangleMesh.create_box(*(b_hi - b_lo))
        box.translate(b_lo)
        box.compute_triangle_normals()
        pieces.append(box)
    return pieces


def procedural_variant(base: SimScene, rng: np.random.Generator, cfg: SimulationConfig) -> SimScene:
    """A plausible but different version of a procedural scene: the other objects, grouped where they touch (a table
    with its legs and what stands on it), move horizontally by up to ``variant_shift_m``; the structure moves too
    (``_structure_moves``: walls, ceiling, facades); with ``opening_probability`` a room's wall gains a door-sized
    opening; every material is re-drawn (colours within 0.2, a new texture seed)."""
    objs = base.objects
    boxes = [_bounds(o.mesh) for o in objs]
    parent = list(range(len(objs)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    movable = [i for i, o in enumerate(objs) if not _structural(o.name)]
    for a in movable:
        for b in movable:
            if a < b and np.all(boxes[a][0] - 0.05 <= boxes[b][1]) and np.all(boxes[b][0] - 0.05 <= boxes[a][1]):
                parent[root(a)] = root(b)
    shifts: dict[int, np.ndarray] = {}
    structure = _structure_moves(objs, rng, cfg)
    walls = [i for i, o in enumerate(objs) if o.name.startswith("wall_")]
    opening = int(walls[int(rng.integers(len(walls)))]) if walls and rng.random() < cfg.opening_probability else -1
    objects = []
    for i, o in enumerate(objs):
        meshes = [o.mesh]
        move = None
        if i in movable and cfg.variant_shift_m > 0:
            g = root(i)
            if g not in shifts:
                ang, rad = rng.uniform(0, 2 * np.pi), cfg.variant_shift_m * np.sqrt(rng.random())
                shifts[g] = np.array([np.cos(ang) * rad, np.sin(ang) * rad, 0.0])
            move = shifts[g]
        elif i in structure:
            move = structure[i]
        if i == opening:
            meshes = _with_opening(o.mesh, rng)
        for m in meshes:
            if move is not None:
                m = o3d.geometry.TriangleMesh(m)
                m.translate(move)
            objects.append(SceneObject(o.name, m, o.material))
    materials = []
    for m in base.materials:
        ja, jb = rng.uniform(-0.2, 0.2, 3), rng.uniform(-0.2, 0.2, 3)
        materials.append(Material(m.pattern, tuple(float(x) for x in np.clip(np.asarray(m.color_a) + ja, 0, 1)),
                                  tuple(float(x) for x in np.clip(np.asarray(m.color_b) + jb, 0, 1)), m.scale,
                                  int(rng.integers(1 << 30))))
    return SimScene(base.kind, base.seed, objects, materials, base.light, base.sky, base.camera_c2w,
                    base.camera_fov_x_deg)


class SimulationSynthesizer(_SimulationRole):

    def synthesize(self, request: SynthesisRequest) -> np.ndarray:
        """The frames of ``simulate`` for a clip whose conditioning image was taken at the requested start."""
        return self.simulate(request).frames

    def simulate(self, request: SynthesisRequest, start: ClipStart | None = None) -> SimulatedClip:
        """The clip and its hidden truth. ``start``: where the conditioning image was really taken and what it
        shows (the previous clip's last frame's truth); None: at the requested start, showing the true scene."""
        H, W = _check_request(request)
        cfg, truth = self.config, self.truth
        K = truth.intrinsics_for(H, W)
        req = np.asarray(request.trajectory, dtype=np.float64)
        T = len(req)
        if not cfg.honest:
            true_c2w = req.copy()
            r = render_many(truth.scene, truth.gt_pose(true_c2w), K, supersample=cfg.supersample)
            return SimulatedClip(r.rgb, true_c2w, r.depth * truth._scale(), np.ones(T, dtype=np.float32))
        rng = _rng(request.seed)
        start = start if start is not None else ClipStart(req[0])
        true_c2w = _drifted(np.asarray(start.c2w, dtype=np.float64) @ (invert_pose(req[0]) @ req), cfg, rng)
        true_c2w[0] = start.c2w  # frame 0 is the conditioning image
        poses_gt = truth.gt_pose(true_c2w)
        w = truth._scale()
        tree = _cloud_tree(truth, request.cloud_points)
        variant = (variant_of(truth.scene, int(rng.integers(1 << 31)), cfg) if cfg.hallucinate else None)
        field = AnchorField.draw(rng) if variant is not None else None  # one per clip: hallucinations stay put
        frames = np.empty((T, H, W, 3), dtype=np.uint8)
        depth = np.empty((T, H, W), dtype=np.float32)
        quality = np.empty(T, dtype=np.float32)
        frames[0] = request.image
        depth[0] = (start.depth if start.depth is not None
                    else render(truth.scene, poses_gt[0], K, colour=False).depth * w)
        quality[0] = start.quality
        clear = truth.scene.distance(poses_gt[1:, :3, 3])
        rc, _ = truth.scene.raycasting()
        inside = rc.compute_occupancy(o3d.core.Tensor(poses_gt[1:, :3, 3].astype(np.float32))).numpy() > 0
        # every frame's true view in one batched cast; where the clip hallucinates, the variant's view of those
        # pixels only (each pixel is rendered on its own: the same values as whole-frame renders)
        r = render_many(truth.scene, poses_gt[1:], K, supersample=cfg.supersample)
        true_px = np.ones((T - 1, H, W), dtype=bool)
        if variant is not None:
            true_px = ~r.hit | anchored(tree, r.depth, r.hit, poses_gt[1:], K, cfg, rng, field)
            if not true_px.all():
                v = render_many(variant, poses_gt[1:], K, supersample=cfg.supersample, pixels=~true_px)
        for i in range(1, T):  # the per-frame random draws, in their order
            j = i - 1
            rgb, d = r.rgb[j].astype(np.float64), r.depth[j].astype(np.float64)
            fake = ~true_px[j]
            if fake.any():
                rgb[fake] = v.rgb[j][fake]
                d[fake] = v.depth[j][fake]
            severity = 1.0 if inside[j] else closeup_severity(r.depth[j], r.hit[j], clear[j], cfg)
            if severity > 0:
                rgb, d = _corrupt(rgb, d, severity, rng)
            frames[i] = np.clip(rgb + 0.5, 0, 255).astype(np.uint8)
            depth[i] = d * w
            quality[i] = float(true_px[j].mean()) * (1.0 - severity)
        return SimulatedClip(frames, true_c2w, depth, quality)


def _drifted(poses: np.ndarray, cfg: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
    """``poses`` with a camera-following error growing linearly from 0 (frame 0) to its end size: a rotation
    about a random axis (in the camera frame) and a displacement in a random direction, of half-normal sizes
    with means ``drift_rot_deg`` and ``drift_trans`` x the path length."""
    T = len(poses)
    out = poses.copy()
    if T < 2:
        return out
    half_normal = np.sqrt(np.pi / 2)  # |N(0, 1)| has mean sqrt(2 / pi)
    axis = rng.normal(size=3)
    angle = np.deg2rad(cfg.drift_rot_deg) * abs(rng.normal()) * half_normal
    direction = rng.normal(size=3)
    direction /= max(np.linalg.norm(direction), 1e-12)
    length = float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())
    shift = cfg.drift_trans * length * abs(rng.normal()) * half_normal
    for i in range(1, T):
        f = i / (T - 1)
        out[i, :3, :3] = poses[i, :3, :3] @ axis_angle_to_matrix(axis, angle * f)
        out[i, :3, 3] = poses[i, :3, 3] + direction * shift * f
    return out


def _cloud_tree(truth: SimulationTruth, cloud_points: np.ndarray):
    from scipy.spatial import cKDTree

    pts = np.asarray(cloud_points, dtype=np.float64).reshape(-1, 3)
    return cKDTree(truth.gt_points(pts)) if len(pts) else None


@dataclass(frozen=True)
class AnchorField:
    """The smooth random field over the ground-truth world that decides, under soft anchoring, which surface points
    a clip shows as they are (``anchored``): a few random plane waves of 0.5-2 m wavelength, unit variance, mapped
    through the normal CDF to roughly uniform values. One field per clip, so a surface point is shown (or
    hallucinated) the same way in every frame of the clip: a video model is temporally consistent within a clip,
    its hallucinations stay put."""

    waves: np.ndarray  # [n, 3] wave vectors (rad / m)
    phases: np.ndarray  # [n]

    @classmethod
    def draw(cls, rng: np.random.Generator, n: int = 6) -> AnchorField:
        dirs = rng.normal(size=(n, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        k = 2 * np.pi / rng.uniform(0.5, 2.0, n)
        return cls(dirs * k[:, None], rng.uniform(0, 2 * np.pi, n))

    def uniform(self, pts: np.ndarray) -> np.ndarray:
        """Roughly uniform values in (0, 1) at the points ``pts [N, 3]`` (ground-truth frame, metres)."""
        from scipy.special import ndtr

        return ndtr(np.sqrt(2.0 / len(self.phases)) * np.sin(pts @ self.waves.T + self.phases).sum(1))


def anchored(tree, depth: np.ndarray, hit: np.ndarray, c2w_gt: np.ndarray, K: Intrinsics, cfg: SimulationConfig,
             rng: np.random.Generator, field: AnchorField | None = None) -> np.ndarray:
    """Pixels that show the truth: with ``cfg.anchor_falloff_m`` > 0 (soft anchoring), a pixel whose true surface
    point lies d from the cloud (ground-truth frame) does with probability exp(-d / falloff), decided by ``field``
    at that point (the clip's, so the decision holds in every frame; None: a fresh one from ``rng``), so unanchored
    content comes in patches; with 0, those within ``anchor_tolerance_m`` (hard). ``depth``, ``hit`` ``[H, W]``
    at ``c2w_gt [4, 4]``, or ``[T, H, W]`` at ``[T, 4, 4]``: a clip's frames in one query."""
    out = np.zeros(hit.shape, dtype=bool)
    if tree is None or not hit.any():
        return out
    soft = cfg.anchor_falloff_m > 0
    bound = 10 * cfg.anchor_falloff_m if soft else cfg.anchor_tolerance_m
    H, W = hit.shape[-2:]
    poses = np.asarray(c2w_gt).reshape(-1, 4, 4)
    pts = np.concatenate([unproject_depth(dd.astype(np.float64), c, K.K, mask=m)[0] for dd, m, c in
                          zip(depth.reshape(-1, H, W), hit.reshape(-1, H, W), poses, strict=True)])
    if not soft:
        d, _ = tree.query(pts, k=1, distance_upper_bound=bound, workers=-1)
        out[hit] = np.isfinite(d)
        return out
    u = (field if field is not None else AnchorField.draw(rng)).uniform(pts)
    d = _deciding_distances(tree, pts, u, cfg.anchor_falloff_m, bound)
    out[hit] = np.isfinite(d) & (u < np.exp(-np.where(np.isfinite(d), d, bound) / cfg.anchor_falloff_m))
    return out


def _deciding_distances(tree, pts: np.ndarray, u: np.ndarray, falloff: float, bound: float) -> np.ndarray:
    """The distances of ``pts`` to the cloud (``tree``) that can decide soft anchoring (``u < exp(-d / falloff)``),
    inf for the rest: a point is queried only out to a little beyond the distance where its ``u`` stops anchoring it,
    ``-falloff ln u`` (and at most ``bound``), so most queries stop early (the points grouped by that reach, one
    query per group). Where a point's distance is returned it is the same number as an unbounded query's (the
    nearest point's distance, computed the same way); where it is not, the point lies farther than its reach, so
    ``u < exp(-d / falloff)`` is false for it (by a margin of 1e-6 of the reach plus 1e-9 m, far above rounding):
    the anchoring decisions are exactly those of one query out to ``bound``."""
    with np.errstate(divide="ignore"):
        reach = np.minimum(-falloff * np.log(u) * (1 + 1e-6) + 1e-9, bound)
    uppers = [*(falloff * np.array([0.25, 0.5, 1.0, 2.0, 4.0])), bound]
    group = np.searchsorted(uppers[:-1], reach)  # reach <= uppers[group]
    d = np.full(len(pts), np.inf)
    for g, upper in enumerate(uppers):
        idx = np.flatnonzero(group == g)
        if len(idx):
            d[idx] = tree.query(pts[idx], k=1, distance_upper_bound=min(upper, bound), workers=-1)[0]
    return d


def closeup_severity(depth: np.ndarray, hit: np.ndarray, clearance: float, cfg: SimulationConfig) -> float:
    """How corrupted a frame comes out (0-1): with ``corrupt_near_m`` > 0, by the fraction of the frame filled by
    a surface nearer than it (0 up to ``corrupt_fill[0]``, 1 from ``corrupt_fill[1]``, linear between); with 0, by
    the camera's ``clearance`` against ``corrupt_clearance_m``."""
    if cfg.corrupt_near_m > 0:
        fill = float((hit & (depth < cfg.corrupt_near_m)).mean())
        lo, hi = cfg.corrupt_fill
        return float(np.clip((fill - lo) / max(hi - lo, 1e-9), 0.0, 1.0))
    if cfg.corrupt_clearance_m:
        return float(np.clip(1.0 - clearance / cfg.corrupt_clearance_m, 0.0, 1.0))
    return 0.0


def _smooth_field(rng: np.random.Generator, H: int, W: int, cells: int = 4) -> np.ndarray:
    """A smooth random field [H, W] of unit standard deviation at its ``cells x cells`` knots (bilinear)."""
    g = rng.normal(size=(cells + 1, cells + 1))
    ys, xs = np.linspace(0, cells, H), np.linspace(0, cells, W)
    rows = np.stack([np.interp(xs, np.arange(cells + 1), g[j]) for j in range(cells + 1)])  # [cells+1, W]
    return np.stack([np.interp(ys, np.arange(cells + 1), rows[:, x]) for x in range(W)], axis=1)


def _corrupt(rgb: np.ndarray, depth: np.ndarray, severity: float,
             rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A frame from too close: smeared towards an 8 x 8 blob of its colours with noise, depth distorted."""
    H, W, _ = rgb.shape
    ys, xs = (np.arange(H) * 8) // H, (np.arange(W) * 8) // W
    coarse = np.zeros((8, 8, 3))
    np.add.at(coarse, (ys[:, None], xs[None, :]), rgb)
    counts = np.zeros((8, 8))
    np.add.at(counts, (ys[:, None], xs[None, :]), 1.0)
    blob = (coarse / np.maximum(counts, 1)[..., None])[ys[:, None], xs[None, :]]
    out = (1 - severity) * rgb + severity * (blob + rng.normal(0.0, 25.0, rgb.shape))
    d = depth * np.clip(1.0 + severity * 0.5 * _smooth_field(rng, H, W), 0.2, None)
    return out, d


def _check_request(request: SynthesisRequest) -> tuple[int, int]:
    """(H, W) of a request whose images and cameras have the shapes of the ``SynthesisRequest`` contract: a
    uint8 conditioning image [H, W, 3], a trajectory [T, 4, 4] (T >= 1), and the reference frame either absent
    or given whole (an image like the conditioning image, with its [4, 4] world c2w)."""
    image = np.asarray(request.image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"request.image must be uint8 [H, W, 3], got {image.dtype} {image.shape}")
    traj = np.asarray(request.trajectory)
    if traj.ndim != 3 or traj.shape[1:] != (4, 4) or len(traj) == 0:
        raise ValueError(f"request.trajectory must be [T, 4, 4] with T >= 1, got {traj.shape}")
    if (request.reference_image is None) != (request.reference_c2w is None):
        raise ValueError("request.reference_image and request.reference_c2w come together (the input photo and "
                         "its camera) or not at all")
    if request.reference_image is not None:
        ref = np.asarray(request.reference_image)
        if ref.shape != image.shape or ref.dtype != np.uint8:
            raise ValueError(f"request.reference_image must be uint8 {image.shape} like request.image, got "
                             f"{ref.dtype} {ref.shape}")
        if np.shape(request.reference_c2w) != (4, 4):
            raise ValueError(f"request.reference_c2w must be [4, 4], got {np.shape(request.reference_c2w)}")
    return image.shape[0], image.shape[1]


class SimulationGeometry(_SimulationRole):

    def predict(self, frames: np.ndarray, *, seed: int, hint_c2w: np.ndarray | None = None,
                hint_intrinsics: Intrinsics | None = None,
                hint_depth: list[np.ndarray | None] | None = None) -> GeometryPrediction:
        """``hint_c2w``: the frames' true world cameras (the stored truth of the synthesize step, or the input
        camera); ``hint_depth``: per frame the depth (world units) of what it shows, None to use the true scene's."""
        S, H, W = frames.shape[:3]
        hint = _require_hint(hint_c2w, S)
        if hint_depth is not None and len(hint_depth) != S:
            raise ValueError(f"hint_depth has {len(hint_depth)} entries for {S} frames")
        cfg, rng = self.config, _rng(seed)
        scale = float(np.exp(rng.normal(0.0, cfg.scale_sigma)))  # this call's units per metre
        # relative poses to view 0, in metres, then in this call's units
        gt = self.truth.gt_pose_or_photo(hint)
        rel = invert_pose(gt[0]) @ gt
        rel[0] = np.eye(4)  # exactly, as VGGT's first frame
        rel[:, :3, 3] *= scale
        K_true = self.truth.intrinsics_for(H, W)
        depth = np.zeros((S, H, W), dtype=np.float32)
        conf = np.zeros((S, H, W), dtype=np.float32)
        c2w = np.empty((S, 4, 4))
        Ks = np.empty((S, 3, 3))
        clip_err = ClipDepthError.draw(rng, cfg) if cfg.honest else None  # shared by every frame of this call
        for i in range(S):
            shown = None if hint_depth is None else hint_depth[i]
            if shown is None:
                d_m = render(self.truth.scene, gt[i], K_true, colour=False).depth.astype(np.float64)
            else:
                d_m = np.asarray(shown, dtype=np.float64) / self.truth._scale()
            hit = d_m > 0
            err = 1.0 + rng.normal(0.0, cfg.depth_noise, (H, W))
            if cfg.honest and cfg.depth_lowfreq > 0:
                err *= np.clip(1.0 + cfg.depth_lowfreq * _smooth_field(rng, H, W), 0.5, None)
            if clip_err is not None and hit.any():
                err *= clip_err.factor(d_m, hit, gt[i], K_true)
            depth[i] = np.where(hit, d_m * scale * err, 0.0)
            conf[i] = np.where(hit, np.where(_discontinuity(d_m, hit), cfg.edge_confidence, 1.0), 0.0)
            pose = rel[i].copy()
            if i > 0:
                axis = rng.normal(size=3)
                pose[:3, :3] = axis_angle_to_matrix(axis, np.deg2rad(rng.normal(0, cfg.pose_rot_deg))) @ pose[:3, :3]
                sigma = cfg.pose_trans * scale
                if cfg.honest:
                    sigma = np.hypot(sigma, cfg.pose_trans_rel * np.linalg.norm(rel[i, :3, 3]))
                pose[:3, 3] += rng.normal(0.0, sigma, 3)
            c2w[i] = pose
            f = 1.0 + rng.normal(0.0, cfg.focal_noise)
            Ks[i] = K_true.K
            Ks[i, 0, 0] *= f
            Ks[i, 1, 1] *= f
        return GeometryPrediction(c2w=c2w, K=Ks, depth=depth, confidence=conf,
                                  extras={"simulation_scale": scale})


@dataclass(frozen=True)
class ClipDepthError:
    """The depth error one geometry call (a clip) shares across its frames (honest preset): a smooth
    multiplicative field over the ground-truth world (a few random plane waves of 1-4 m wavelength, unit
    variance, times ``depth_clip_bias``), so the same surface gets the same error from every frame of the clip,
    and a shape bias ``b`` stretching depth about the clip's median: d -> d (1 + b ln(d / median))."""

    waves: np.ndarray  # [n, 3] wave vectors (rad / m)
    phases: np.ndarray  # [n]
    bias: float
    shape: float

    @classmethod
    def draw(cls, rng: np.random.Generator, cfg: SimulationConfig, n: int = 4) -> ClipDepthError:
        dirs = rng.normal(size=(n, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        k = 2 * np.pi / rng.uniform(1.0, 4.0, n)
        return cls(dirs * k[:, None], rng.uniform(0, 2 * np.pi, n), cfg.depth_clip_bias,
                   float(rng.normal(0.0, cfg.depth_clip_shape)))

    def factor(self, depth_m: np.ndarray, hit: np.ndarray, c2w_gt: np.ndarray, K: Intrinsics) -> np.ndarray:
        """Multiplicative error ``[H, W]`` of a frame with true z-depth ``depth_m`` at ``c2w_gt``."""
        out = np.ones(depth_m.shape)
        pts, idx = unproject_depth(depth_m, c2w_gt, K.K, mask=hit)
        if not len(pts):
            return out
        field = np.sqrt(2.0 / len(self.phases)) * np.sin(pts @ self.waves.T + self.phases).sum(1)
        d = depth_m.reshape(-1)[idx]
        shape = self.shape * np.log(d / np.median(d))
        out.reshape(-1)[idx] = np.clip(1.0 + self.bias * field + shape, 0.5, None)
        return out


def _discontinuity(depth: np.ndarray, hit: np.ndarray, rel: float = 0.05) -> np.ndarray:
    """Pixels next to a relative depth jump larger than ``rel`` or to a miss."""
    d = np.where(hit, depth, 0.0)
    edge = np.zeros_like(hit)
    for axis in (0, 1):
        a = np.take(d, range(1, d.shape[axis]), axis=axis)
        b = np.take(d, range(0, d.shape[axis] - 1), axis=axis)
        jump = np.abs(a - b) > rel * np.maximum(np.minimum(a, b), 1e-6)
        jump |= (a == 0) != (b == 0)
        if axis == 0:
            edge[1:] |= jump
            edge[:-1] |= jump
        else:
            edge[:, 1:] |= jump
            edge[:, :-1] |= jump
    return edge & hit


class SimulationMonoDepth(_SimulationRole):

    def predict(self, image: np.ndarray, *, seed: int, hint_c2w: np.ndarray | None = None,
                hint_intrinsics: Intrinsics | None = None,
                hint_depth: np.ndarray | None = None) -> MonoDepthPrediction:
        """``hint_c2w``: the image's true world camera; ``hint_depth``: the depth (world units) of what it shows
        (None: the true scene's)."""
        H, W = image.shape[:2]
        hint = _require_hint(hint_c2w, 1)
        gt = self.truth.gt_pose_or_photo(hint)[0]
        if hint_depth is None:
            r = render(self.truth.scene, gt, self.truth.intrinsics_for(H, W), colour=False)
            d_m, hit = r.depth.astype(np.float64), r.hit
        else:
            d_m = np.asarray(hint_depth, dtype=np.float64) / self.truth._scale()
            hit = d_m > 0
        rng = _rng(seed)
        inv = np.where(hit, 1.0 / np.maximum(d_m, 1e-6), 0.0)
        a = float(np.exp(rng.normal(0.0, 1.0)))
        b = float(rng.uniform(0.0, 0.2)) * a * float(np.median(inv[hit])) if hit.any() else 0.0
        noisy = inv * (1.0 + rng.normal(0.0, 2 * self.config.depth_noise, inv.shape))
        if self.config.honest and self.config.depth_lowfreq > 0:
            noisy *= np.clip(1.0 + self.config.depth_lowfreq * _smooth_field(rng, H, W), 0.5, None)
        rel = np.where(hit, a * noisy + b, 0.0).astype(np.float32)
        return MonoDepthPrediction(inv_depth=rel, sky=~hit if self.truth.scene.sky else np.zeros_like(hit))


class SimulationRefiner(_SimulationRole):
    """The refiner stand-in: moves a render ``refine_strength`` of the way towards a target view and adds noise.
    The target is the true view where the scene was observed (``observe``: the cloud the fit was made from; the same
    anchoring as the synthesizer) and, with ``refine_observed_only`` (honest), a variant of the scene elsewhere: a
    diffusion refiner repairs artifacts, it does not know unseen content. Before ``observe`` (or with the perfect
    preset) every pixel counts as observed."""

    def __init__(self, truth: SimulationTruth, config: SimulationConfig) -> None:
        super().__init__(truth, config)
        self._tree = None
        self._observed = False

    def observe(self, cloud_points: np.ndarray) -> None:
        """The cloud (world frame) whose content counts as observed."""
        self._tree = _cloud_tree(self.truth, cloud_points)
        self._observed = True

    def refine(self, rendered: np.ndarray, reference: np.ndarray | None, *, seed: int,
               hint_c2w: np.ndarray | None = None, hint_intrinsics: Intrinsics | None = None) -> np.ndarray:
        H, W = rendered.shape[:2]
        gt_pose = self.truth.gt_pose(_require_hint(hint_c2w, 1))[0]
        K = hint_intrinsics if hint_intrinsics is not None else self.truth.intrinsics_for(H, W)
        if (K.height, K.width) != (H, W):
            raise ValueError(f"hint_intrinsics are for {K.width}x{K.height}, the render is {W}x{H}")
        cfg = self.config
        r_true = render(self.truth.scene, gt_pose, K, supersample=max(2, cfg.supersample))
        truth = r_true.rgb
        rng = _rng(seed)
        if cfg.honest and cfg.refine_observed_only and self._observed:
            seen = ~r_true.hit | anchored(self._tree, r_true.depth, r_true.hit, gt_pose, K, cfg, rng)
            if not seen.all():
                variant = variant_of(self.truth.scene, int(rng.integers(1 << 31)), cfg)
                v = render_many(variant, gt_pose[None], K, supersample=max(2, cfg.supersample),
                                pixels=~seen[None]).rgb[0]  # only the unseen pixels are used
                truth = np.where(seen[..., None], truth, v)
        r, t = rendered.astype(np.float64) / 255.0, truth.astype(np.float64) / 255.0
        out = r + cfg.refine_strength * (t - r)
        if cfg.refine_noise > 0:
            out = out + rng.normal(0.0, cfg.refine_noise, out.shape)
        return np.round(np.clip(out, 0.0, 1.0) * 255).astype(np.uint8)


def simulation_backend(truth: SimulationTruth, config: SimulationConfig) -> Backend:
    return Backend(name=BACKEND, synthesizer=SimulationSynthesizer(truth, config),
                   geometry=SimulationGeometry(truth, config), mono_depth=SimulationMonoDepth(truth, config),
                   refiner=SimulationRefiner(truth, config))
