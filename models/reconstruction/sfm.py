"""Structure from motion of a (generated) video: its camera path recovered with COLMAP through pycolmap, for the
camera-guidance metric (``models/metrics/pose.py``: the paper's RotErr / TransErr, as introduced by CameraCtrl).

**Pose recovery** (:func:`recover_poses`) runs COLMAP's sparse structure-from-motion through pycolmap,
as a **ladder** of attempts (:class:`Attempt`; default :data:`ROBUST`, the old single run is :data:`STOCK`):

1. the frames are written as PNGs to ``workdir/images`` (``frame_00000.png`` ...; ``images_x2`` for a rung
   that upscales them, with ``K`` scaled alike);
2. ``pycolmap.extract_features`` computes SIFT features on the CPU into ``workdir/database.db`` (later rungs
   with other feature or matching settings: ``workdir/attempts/<k>-<name>/database.db``; rungs that differ
   only in mapper settings share a database);
3. features are matched. Short clips (``<= EXHAUSTIVE_MAX_FRAMES`` frames, which covers the 14- and
   25-frame clips of video diffusion models) use **exhaustive** matching: every pair is tried, so
   wide-baseline pairs (first vs. last frame) are available to the mapper's initialisation and to
   triangulation, and the cost is negligible (25 frames = 300 pairs). Longer videos use COLMAP's
   **sequential** matcher (each frame against the next ``overlap`` frames, plus quadratically spaced
   ones), which is COLMAP's recommended mode for ordered video frames;
4. ``pycolmap.incremental_mapping`` reconstructs; when it yields several models, the one with the most
   registered images (then the lowest reprojection error) is used.

The default ladder (:data:`ROBUST`): (a) COLMAP's **global** mapper (GLOMAP: rotation averaging, global
positioning, bundle adjustment; ``pycolmap.global_mapping``) and (b) its incremental mapper with COLMAP's
defaults (``stock``), both on the same features and matches and both always run; (c) the incremental mapper set
for short, small-baseline clips (:data:`SHORT_CLIP`: initial pair from 8 deg of triangulation angle and 50
inliers instead of 16 deg and 100, registration from 15 inliers, triangulation from 1 deg); (d) the global and
(e) the short-clip mapper on SIFT features of the frames upscaled x2 (finer keypoints at 256 px, at 3-10x the
cost). After ``MIN_RUNGS`` (2) rungs, a result that registers every frame with a mean reprojection error of at
most ``GOOD_REPROJECTION_PX`` (0.4 px) ends the ladder; the result with the most registered frames, then the
lowest reprojection error, wins. ``PoseRecovery.attempt`` names the winner (``matcher`` its matcher) and
``.attempts`` lists every rung tried (registered frames, error, seconds, reason).

Why a ladder (measured on simulated RealEstate10K-format clips, 640x360 rendered, read at 256² by the
dataset reader; ``benchmarks/pose_floor.py``, development seeds 0-2). The reader's intrinsics after the
resize and centre crop are right (re-rendering with them reproduces the frames; one pixel or 1 % off does
not; tested), so the large errors are COLMAP's: (i) at 256² a 15-frame clip often has fewer than 100 inliers
per pair or less than 16 deg of parallax for the incremental mapper's initial pair, and the reconstruction
fails (0 registered) or stops early; (ii) worse, the incremental mapper can register *every* frame and still
be wrong by 1-20 deg per frame: on forward (dolly) motion it converged to a wrong solution (a steady
rotation drift, 1.0 px reprojection error) from every initial pair and setting tried, although the true
poses explain the same matches to 0.08 px (Sampson); the global mapper, which starts from all pairs'
relative rotations at once, found the right one (0.33 px). Wrong reconstructions show a higher mean
reprojection error (0.5-1.1 px against 0.25-0.45 px for right ones), which is what the ladder keys on; lower
SIFT peak thresholds and guided matching fixed some clips and broke others (wrong matches on repeated
texture) and are not in the default ladder. COLMAP with 2 threads is not bit-repeatable run to run (per-frame
errors of a right reconstruction vary by ~0.1 deg; a marginal clip can flip between right and wrong).

**Pure rotation.** A camera that only rotates (a pan) gives no parallax: nothing can be triangulated. The
incremental mapper registers a few frames or none (its two-view geometry labels such pairs ``PANORAMIC``);
the global mapper registers them all, with rotations off by 0.4-1.7 deg per frame and meaningless camera
centres (T_err 0.2-0.4 of the extent on a requested pan). So with a known ``K`` (``rotation_fallback=True``)
:func:`recover_poses` also fits the model that such a video does determine: every camera at one centre,
rotations fitted to the verified matches of the first rung (``x_j ~ K R_j R_i^T K^-1 x_i``: per-pair RANSAC
on two-point Kabsch fits, a maximum-inlier spanning tree from frame 0, then a joint robust least-squares
refinement on the pixel residuals of all pairs). It is accepted only if it explains *all* verified matches
to keypoint-noise level (median residual <= ``ROTATION_MAX_MEDIAN_PX`` = 0.75 px, 90th percentile <=
``ROTATION_MAX_P90_PX`` = 2 px; the moving cameras of the other clips leave medians of 0.7-7 px and 90th
percentiles of 3.8-25 px), registers no fewer frames than structure from motion, and no incremental rung
registered every frame at a right reconstruction's reprojection error (<= ``GOOD_REPROJECTION_PX``: that mapper
initialises only from a pair with enough triangulation angle, so a clip it reconstructs whole and well has
parallax). The first version of the ladder lacked this test and, on held-out seed 11, took a rotation for a street
orbit whose far geometry left little parallax (3.3 deg per frame); the second demanded only that every frame
register and, on held-out seed 21, kept a wrong incremental reconstruction (0.81 px) of a pan (58.8 deg per frame);
see ``benchmarks/pose_floor.py``. The result then has
``model="rotation"``, ``attempt="rotation-only"`` and every camera centre at the origin (a requested pan
then has T_err 0; a requested translation shows up as its full T_err). When the matches hold no measurable
parallax, structure from motion's translations are not determined by the data either, so the rotation model
is the honest answer. ``model="sfm"`` otherwise.

Intrinsics: with a known ``K`` the frames share one COLMAP ``PINHOLE`` camera (``fx, fy, cx, cy``) and
bundle adjustment does not refine it (no focal, principal-point or extra-parameter refinement, neither
in bundle adjustment nor in absolute-pose registration). Without ``K`` the frames share one
``SIMPLE_RADIAL`` camera (``f, cx, cy, k``) initialised by COLMAP from the image size
(focal = 1.2 x max(W, H)) and refined by bundle adjustment. COLMAP's pixel convention (pixel centre at
``+0.5``) is navcrafter's, so ``K`` is passed unchanged.

COLMAP stores world-to-camera poses (``Image.cam_from_world()``, a ``Rigid3d``; in pycolmap 4.x it is a
*method*, because an image's pose is derived from its frame/rig) in the OpenCV camera convention (x right,
y down, z forward), the same camera axes as navcrafter; :func:`recover_poses` inverts them to
camera-to-world. The reconstruction's world frame and scale are arbitrary (gauge freedom), which is why
the metric (``models/metrics/pose.py``) is computed relative to the first frame and with the translation scale
normalised.

Failure is a result, not an exception: if COLMAP finds no reconstruction, :func:`recover_poses` returns
zero registered frames and a ``reason``.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from navcrafter.models.camera.cameras import invert_pose

EXHAUSTIVE_MAX_FRAMES = 25
MatcherMode = Literal["auto", "exhaustive", "sequential"]


@dataclass(frozen=True)
class Attempt:
    """One rung of the recovery ladder: COLMAP settings that differ from its defaults (``None`` = default).

    Features: ``peak_threshold`` (SIFT's DoG contrast threshold; lower finds more, weaker keypoints),
    ``dsp`` (domain-size pooling and affine shape: DSP-SIFT descriptors), ``upscale`` (the frames are resampled
    by this integer factor before extraction, ``K`` scaled with them; poses do not depend on it).
    Matching: ``matcher`` (``"auto"``: the ``matcher`` argument of :func:`recover_poses`), ``guided``
    (guided matching after geometric verification). Mapper: ``init_min_tri_angle`` (degrees; COLMAP's 16 deg
    rejects the small baselines of a 15-frame clip as initial pairs), ``init_min_num_inliers``,
    ``abs_pose_min_num_inliers``, ``abs_pose_min_inlier_ratio``, ``min_tri_angle`` (degrees, the triangulation
    and filtering minimum), ``mapper_options`` (further ``(name, value)`` settings of
    ``IncrementalMapperOptions``), ``global_sfm`` (COLMAP's global mapper instead of the incremental one; the
    incremental mapper settings then do not apply). Seeds and thread counts are arguments of
    :func:`recover_poses`.
    """

    name: str
    matcher: str = "auto"
    peak_threshold: float | None = None
    dsp: bool = False
    upscale: int = 1
    guided: bool = False
    init_min_tri_angle: float | None = None
    init_min_num_inliers: int | None = None
    abs_pose_min_num_inliers: int | None = None
    abs_pose_min_inlier_ratio: float | None = None
    min_tri_angle: float | None = None
    mapper_options: tuple[tuple[str, float], ...] = ()
    global_sfm: bool = False

    def features_key(self, matcher: str) -> tuple:
        return (self.peak_threshold, self.dsp, self.upscale, matcher, self.guided)


#: The settings ``recover_poses`` used before the ladder (COLMAP's defaults, exhaustive matching up to 25 frames).
STOCK: tuple[Attempt, ...] = (Attempt("stock"),)
#: Mapper settings for short, small-baseline clips (15 frames at 256 px): COLMAP's initial pair needs 16 deg
#: of triangulation angle and 100 inliers, registration 30 inliers, triangulation 1.5 deg.
SHORT_CLIP = dict(init_min_tri_angle=8.0, init_min_num_inliers=50, abs_pose_min_num_inliers=15, min_tri_angle=1.0)
#: The default ladder: COLMAP's global mapper (GLOMAP) and its incremental mapper on the same features (both
#: always run), then the incremental mapper set for short clips, then features of the frames upscaled x2.
ROBUST: tuple[Attempt, ...] = (
    Attempt("global", global_sfm=True),
    Attempt("stock"),
    Attempt("short-clip", **SHORT_CLIP),
    Attempt("global-x2", global_sfm=True, upscale=2),
    Attempt("short-clip-x2", upscale=2, **SHORT_CLIP),
)
#: The ladder may stop only after this many rungs.
MIN_RUNGS = 2
#: A rung whose result registers every frame with at most this mean reprojection error (pixels of the input
#: frames) ends the ladder; a worse one lets the next rungs try (wrong reconstructions of these clips register
#: every frame too, at 0.5-1.1 px instead of 0.25-0.45 px).
GOOD_REPROJECTION_PX = 0.4
LADDERS = {"stock": STOCK, "robust": ROBUST}
#: A pure-rotation (panorama) estimate is accepted only if it explains the matches to within these residuals
#: (pixels of the input frames): the data then hold no parallax the pose could be measured from.
ROTATION_MAX_MEDIAN_PX = 0.75
ROTATION_MAX_P90_PX = 2.0


@dataclass
class PoseRecovery:
    """Camera-to-world poses recovered by COLMAP for each input frame (NaN where not registered)."""

    c2w: np.ndarray  # [N, 4, 4] OpenCV camera-to-world in the reconstruction's (arbitrary) frame and scale
    registered: np.ndarray  # [N] bool
    n_frames: int
    n_registered: int
    n_reconstructions: int = 0
    n_points3d: int = 0
    mean_reprojection_error: float = float("nan")  # pixels
    camera_model: str = ""
    camera_params: list[float] = field(default_factory=list)  # COLMAP's parameters of the shared camera
    matcher: str = ""
    reason: str = ""  # empty on success; otherwise why frames (or all of them) did not register
    attempt: str = ""  # name of the ladder rung whose result this is ("rotation-only": the panorama model)
    model: str = ""  # "sfm" (COLMAP's reconstruction) or "rotation" (pure rotation about one centre)
    attempts: list[dict] = field(default_factory=list)  # every rung tried: name, n_registered, error, seconds

    def to_dict(self) -> dict:
        return {"n_frames": self.n_frames, "n_registered": self.n_registered,
                "registered": self.registered.tolist(), "n_reconstructions": self.n_reconstructions,
                "n_points3d": self.n_points3d, "mean_reprojection_error": self.mean_reprojection_error,
                "camera_model": self.camera_model, "camera_params": list(self.camera_params),
                "matcher": self.matcher, "reason": self.reason, "attempt": self.attempt, "model": self.model,
                "attempts": [dict(a) for a in self.attempts]}


def _failed(n: int, reason: str, **kw) -> PoseRecovery:
    return PoseRecovery(np.full((n, 4, 4), np.nan), np.zeros(n, dtype=bool), n, 0, reason=reason, **kw)


def _write_frames(frames: Sequence[np.ndarray] | np.ndarray, folder: Path, upscale: int = 1) -> list[str]:
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for i, frame in enumerate(frames):
        a = np.asarray(frame)
        if a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"frame {i}: expected an HxWx3 image, got shape {a.shape}")
        if a.dtype != np.uint8:
            raise ValueError(f"frame {i}: expected uint8, got {a.dtype}")
        name = f"frame_{i:05d}.png"
        im = Image.fromarray(a)
        if upscale > 1:
            im = im.resize((a.shape[1] * upscale, a.shape[0] * upscale), Image.Resampling.BICUBIC)
        im.save(folder / name)
        names.append(name)
    return names


def recover_poses(frames: Sequence[np.ndarray] | np.ndarray, K: np.ndarray | None, workdir: str | Path, *,
                  matcher: MatcherMode = "auto", num_threads: int = -1, seed: int = 0,
                  min_model_size: int = 3, max_num_features: int = 8192, quiet: bool = True,
                  attempts: str | Sequence[Attempt] = "robust", rotation_fallback: bool = True) -> PoseRecovery:
    """Recover per-frame camera-to-world poses of ``frames`` (``HxWx3`` uint8) with COLMAP.

    ``K``: the frames' shared 3x3 intrinsics (kept fixed), or ``None`` to let COLMAP estimate a shared
    ``SIMPLE_RADIAL`` camera. ``workdir`` is (re)populated with ``images/``, ``database.db``, ``sparse/``
    and ``attempts/`` (later rungs of the ladder); previous contents of those are removed.
    ``matcher="auto"`` is exhaustive up to ``EXHAUSTIVE_MAX_FRAMES`` frames and sequential beyond.
    ``num_threads=-1`` uses all cores. ``seed`` seeds COLMAP's RANSAC and mapper for repeatable results.
    Reconstructions with fewer than ``min_model_size`` registered images are discarded by COLMAP (its
    default, 10, would reject short clips). ``quiet`` hides COLMAP's INFO log lines (warnings and errors
    still show) while it runs.

    ``attempts``: the ladder of COLMAP settings (:class:`Attempt`), ``"robust"`` (:data:`ROBUST`, default)
    or ``"stock"`` (:data:`STOCK`, COLMAP's defaults: the behaviour before the ladder). Rungs run in order
    until one registers every frame with a mean reprojection error of at most ``GOOD_REPROJECTION_PX``;
    the result with the most registered frames (then the lowest mean reprojection error) wins.
    ``rotation_fallback`` (with a known ``K``): also fit a pure rotation about one centre to the verified
    matches and use it if it explains them (module docstring) and registers no fewer frames.
    ``PoseRecovery.attempt`` / ``.attempts`` record what won and
    what was tried. Never raises for a failed reconstruction: it returns zero registered frames and a reason.
    """
    import pycolmap

    ladder = LADDERS[attempts] if isinstance(attempts, str) else tuple(attempts)
    if not ladder:
        raise ValueError("attempts is empty")
    level = pycolmap.logging.minloglevel
    if quiet:
        pycolmap.logging.minloglevel = max(level, int(pycolmap.logging.Level.WARNING.value))
    try:
        return _ladder(frames, K, Path(workdir), matcher, num_threads, seed, min_model_size, max_num_features,
                       ladder, rotation_fallback)
    finally:
        pycolmap.logging.minloglevel = level


def _rank(rec: PoseRecovery) -> tuple:
    err = rec.mean_reprojection_error
    return (rec.n_registered, rec.model == "sfm", -(err if np.isfinite(err) else np.inf))


def _ladder(frames, K, work: Path, matcher: MatcherMode, num_threads: int, seed: int, min_model_size: int,
            max_num_features: int, ladder: tuple[Attempt, ...], rotation_fallback: bool) -> PoseRecovery:
    import time

    n = len(frames)
    if n == 0:
        return _failed(0, "no frames")
    if matcher == "auto":
        matcher = "exhaustive" if n <= EXHAUSTIVE_MAX_FRAMES else "sequential"
    if matcher not in ("exhaustive", "sequential"):
        raise ValueError(f"unknown matcher {matcher!r}; use 'auto', 'exhaustive' or 'sequential'")
    if K is not None:
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be 3x3, got {K.shape}")
    for p in (work / "images", work / "sparse", work / "attempts"):
        if p.exists():
            shutil.rmtree(p)
    (work / "database.db").unlink(missing_ok=True)  # COLMAP appends to an existing database: start clean
    images: dict[int, tuple[Path, list[str]]] = {}
    databases: dict[tuple, Path] = {}
    best: PoseRecovery | None = None
    tried: list[dict] = []
    for k, att in enumerate(ladder):
        t0 = time.perf_counter()
        m = matcher if att.matcher == "auto" else att.matcher
        if att.upscale not in images:
            folder = work / ("images" if att.upscale == 1 else f"images_x{att.upscale}")
            images[att.upscale] = (folder, _write_frames(frames, folder, att.upscale))
        folder, names = images[att.upscale]
        home = work if k == 0 else work / "attempts" / f"{k}-{att.name}"
        key = att.features_key(m)
        fresh = key not in databases
        if fresh:
            databases[key] = home / "database.db"
        rec = _recover(folder, names, K, home, databases[key], fresh, att, m, num_threads, seed, min_model_size,
                       max_num_features)
        tried.append({"name": att.name, "model": "sfm", "matcher": m, "n_registered": rec.n_registered,
                      "mean_reprojection_error": rec.mean_reprojection_error, "n_points3d": rec.n_points3d,
                      "seconds": time.perf_counter() - t0, "reason": rec.reason})
        if best is None or _rank(rec) > _rank(best):
            best = rec
        if k + 1 >= MIN_RUNGS and best.n_registered == n and best.mean_reprojection_error <= GOOD_REPROJECTION_PX:
            break
    assert best is not None
    if rotation_fallback and K is not None:
        t0 = time.perf_counter()
        up = ladder[0].upscale  # the first rung's matches: always its own fresh database, work/database.db
        rot = _rotation_only(work / "database.db", images[up][1], K * _scale_matrix(up), n, upscale=up)
        tried.append({"name": "rotation-only", "model": "rotation", "matcher": best.matcher,
                      "n_registered": rot.n_registered, "mean_reprojection_error": rot.mean_reprojection_error,
                      "n_points3d": 0, "seconds": time.perf_counter() - t0, "reason": rot.reason})
        ran = tried[:-1]  # the ladder's rungs that ran, in order (the last entry is the rotation model's)
        parallax = [t["name"] for t, a in zip(ran, ladder) if not a.global_sfm and t["n_registered"] == n
                    and t["mean_reprojection_error"] <= GOOD_REPROJECTION_PX]
        if parallax:  # an incremental rung triangulated every frame, and well: the clip has parallax
            tried[-1]["reason"] = (f"not used: the incremental mapper ({parallax[0]}) registered every frame at <= "
                                   f"{GOOD_REPROJECTION_PX} px, so the matches hold parallax"
                                   + (f" ({rot.reason})" if rot.reason else ""))
        elif rot.n_registered >= max(best.n_registered, 2):  # accepted, and registers no fewer frames
            rot.camera_params = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]
            rot.matcher = best.matcher
            best = rot
    best.attempts = tried
    return best


def _scale_matrix(upscale: int) -> np.ndarray:
    return np.array([[upscale, 1.0, upscale], [1.0, upscale, upscale], [1.0, 1.0, 1.0]])


def _recover(image_dir: Path, names: list[str], K: np.ndarray | None, home: Path, database: Path, fresh: bool,
             att: Attempt, matcher: str, num_threads: int, seed: int, min_model_size: int,
             max_num_features: int) -> PoseRecovery:
    import pycolmap

    n = len(names)
    index = {name: i for i, name in enumerate(names)}
    sparse = home / "sparse"
    sparse.mkdir(parents=True, exist_ok=True)
    pycolmap.set_random_seed(seed)
    reader = pycolmap.ImageReaderOptions()
    Kf = None if K is None else K * _scale_matrix(att.upscale)
    if Kf is not None:
        reader.camera_model = "PINHOLE"
        reader.camera_params = ",".join(repr(float(v)) for v in (Kf[0, 0], Kf[1, 1], Kf[0, 2], Kf[1, 2]))
    else:
        reader.camera_model = "SIMPLE_RADIAL"
    info = {"matcher": matcher, "camera_model": reader.camera_model, "attempt": att.name, "model": "sfm"}
    if fresh:
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = num_threads
        extraction.use_gpu = False
        extraction.sift.max_num_features = max_num_features
        if att.peak_threshold is not None:
            extraction.sift.peak_threshold = att.peak_threshold
        if att.dsp:
            extraction.sift.domain_size_pooling = True
            extraction.sift.estimate_affine_shape = True
        pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = num_threads
        matching.use_gpu = False
        matching.guided_matching = att.guided
        if matcher == "exhaustive":
            pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.num_threads = num_threads
            pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                      device=pycolmap.Device.cpu)

    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = num_threads
    opts.random_seed = seed
    opts.min_model_size = min(min_model_size, n)
    opts.extract_colors = False
    if K is not None:  # known intrinsics: keep them fixed
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.mapper.abs_pose_refine_focal_length = False
        opts.mapper.abs_pose_refine_extra_params = False
    mp = opts.mapper
    if att.init_min_tri_angle is not None:
        mp.init_min_tri_angle = att.init_min_tri_angle
    if att.init_min_num_inliers is not None:
        mp.init_min_num_inliers = att.init_min_num_inliers
    if att.abs_pose_min_num_inliers is not None:
        mp.abs_pose_min_num_inliers = att.abs_pose_min_num_inliers
    if att.abs_pose_min_inlier_ratio is not None:
        mp.abs_pose_min_inlier_ratio = att.abs_pose_min_inlier_ratio
    if att.min_tri_angle is not None:
        mp.filter_min_tri_angle = att.min_tri_angle
        mp.ba_local_min_tri_angle = min(mp.ba_local_min_tri_angle, 4 * att.min_tri_angle)
        opts.triangulation.min_angle = att.min_tri_angle
    for name, value in att.mapper_options:
        setattr(mp, name, value)
    try:
        if att.global_sfm:
            recs = pycolmap.global_mapping(database, image_dir, sparse, options=_global_options(K, n, num_threads,
                                                                                                seed, min_model_size))
        else:
            recs = pycolmap.incremental_mapping(database, image_dir, sparse, options=opts)
    except Exception as e:  # a failed reconstruction is a result, not an error
        return _failed(n, f"COLMAP incremental mapping failed: {type(e).__name__}: {e}", **info)
    if not recs:
        return _failed(n, "COLMAP found no reconstruction (too few matches or too little parallax)", **info)
    rec = max(recs.values(), key=lambda r: (r.num_reg_images(), -r.compute_mean_reprojection_error()))

    c2w = np.full((n, 4, 4), np.nan)
    registered = np.zeros(n, dtype=bool)
    for image in rec.images.values():
        i = index.get(image.name)
        if i is None or not image.has_pose:
            continue
        w2c = np.eye(4)
        w2c[:3, :] = image.cam_from_world().matrix()
        c2w[i] = invert_pose(w2c)
        registered[i] = True
    camera = next(iter(rec.cameras.values()))
    params = np.array(camera.params, dtype=np.float64)
    if att.upscale > 1:  # report the camera in pixels of the input frames
        params[: 4 if camera.model.name == "PINHOLE" else 3] /= att.upscale
    k = int(registered.sum())
    reason = "" if k == n else f"{n - k} of {n} frames not registered"
    if k == 0:
        reason = "the reconstruction registered no input frame"
    return PoseRecovery(c2w, registered, n, k, n_reconstructions=len(recs), n_points3d=rec.num_points3D(),
                        mean_reprojection_error=float(rec.compute_mean_reprojection_error()) / att.upscale,
                        camera_model=camera.model.name, camera_params=[float(v) for v in params],
                        matcher=matcher, reason=reason, attempt=att.name, model="sfm")


def _global_options(K, n: int, num_threads: int, seed: int, min_model_size: int):
    import pycolmap

    g = pycolmap.GlobalPipelineOptions()
    g.num_threads = num_threads
    g.random_seed = seed
    g.min_model_size = min(min_model_size, n)
    g.mapper.num_threads = num_threads
    g.mapper.random_seed = seed
    g.mapper.global_positioning.use_gpu = False
    g.mapper.bundle_adjustment.ceres.use_gpu = False
    if K is not None:
        g.mapper.bundle_adjustment.refine_focal_length = False
        g.mapper.bundle_adjustment.refine_principal_point = False
        g.mapper.bundle_adjustment.refine_extra_params = False
    return g


def _verified_pairs(database: Path, names: list[str]) -> tuple[dict[int, int], dict[int, np.ndarray], list]:
    """Image id -> frame index, keypoints (xy) per image id, and verified pairs (id1, id2, inlier matches)."""
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        index = {name: i for i, name in enumerate(names)}
        ids = {im.image_id: index[im.name] for im in db.read_all_images() if im.name in index}
        kps = {i: np.asarray(db.read_keypoints(i))[:, :2].astype(np.float64) for i in ids}
        pair_ids, geoms = db.read_two_view_geometries()
        pairs = []
        for pid, g in zip(pair_ids, geoms):
            i1, i2 = pycolmap.pair_id_to_image_pair(pid)
            m = np.asarray(g.inlier_matches)
            if len(m) and i1 in ids and i2 in ids:
                pairs.append((i1, i2, m))
    finally:
        db.close()
    return ids, kps, pairs


def _kabsch(b1: np.ndarray, b2: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """The rotation R minimising sum w |b2 - R b1|^2 (unit bearings, [M, 3])."""
    w = np.ones(len(b1)) if w is None else w
    H = (b2 * w[:, None]).T @ b1
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _project(K: np.ndarray, b: np.ndarray) -> np.ndarray:
    p = b @ K.T
    return p[:, :2] / p[:, 2:3]


def _rotation_only(database: Path, names: list[str], K: np.ndarray, n: int, upscale: int = 1,
                   min_inliers: int = 15, max_matches: int = 150, ransac_trials: int = 200,
                   inlier_px: float = 2.0) -> PoseRecovery:
    """A pure-rotation model of the clip: every camera at one centre, rotations fitted to COLMAP's verified matches.

    For a camera that only rotates, matched pixels obey ``x_j ~ K R_j R_i^T K^-1 x_i`` (the homography of a
    panorama) and no structure-from-motion is possible (no parallax, nothing to triangulate). Relative
    rotations of the verified pairs (Kabsch on the bearings), chained along a maximum-inlier spanning tree
    from frame 0, are refined jointly over all pairs (robust least squares on pixel residuals). The model is
    accepted only if its residuals are at keypoint-noise level (``ROTATION_MAX_MEDIAN_PX`` /
    ``ROTATION_MAX_P90_PX``); otherwise the frames moved and the result says ``rejected``.
    """
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    info = {"camera_model": "PINHOLE", "attempt": "rotation-only", "model": "rotation"}
    ids, kps, pairs = _verified_pairs(database, names)
    Kinv = np.linalg.inv(K)

    def bearings(pts: np.ndarray) -> np.ndarray:
        b = np.c_[pts, np.ones(len(pts))] @ Kinv.T
        return b / np.linalg.norm(b, axis=1, keepdims=True)

    edges = []  # (frame i, frame j, bearings in i, bearings in j, pixels in j, pixels in i)
    for i1, i2, m in pairs:
        if len(m) < min_inliers:
            continue
        f1, f2 = ids[i1], ids[i2]
        x1, x2 = kps[i1][m[:, 0]], kps[i2][m[:, 1]]
        edges.append((f1, f2, bearings(x1), bearings(x2), x2, x1))
    if not edges:
        return _failed(n, "rotation-only: no verified pair with enough matches", **info)
    rng = np.random.default_rng(0)
    rel, kept = {}, []
    for f1, f2, b1, b2, x2, x1 in edges:  # RANSAC (2-point Kabsch) per pair, then a refit on its inliers
        best = np.zeros(len(b1), dtype=bool)
        for _ in range(ransac_trials):
            pick = rng.choice(len(b1), 2, replace=False)
            R = _kabsch(b1[pick], b2[pick])
            inl = np.linalg.norm(_project(K, b1 @ R.T) - x2, axis=1) <= inlier_px * upscale
            if inl.sum() > best.sum():
                best = inl
        if best.sum() < min_inliers:
            continue
        rel[(f1, f2)] = _kabsch(b1[best], b2[best])
        kept.append((f1, f2, b1[best], b2[best], x2[best], x1[best]))
    if not kept:
        return _failed(n, "rejected: no verified pair is consistent with a rotation", **info)
    total, inliers = sum(len(e[2]) for e in edges), sum(len(e[2]) for e in kept)
    if inliers < 0.85 * total:  # the joint fit cannot do better than each pair alone: the p90 test would fail
        return _failed(n, f"rejected: a rotation explains only {inliers} of {total} verified matches within "
                       f"{inlier_px:g} px, pair by pair: the camera moved", **info)
    all_edges, edges = edges, kept
    # maximum spanning tree (by inlier count) from frame 0 (or the lowest connected frame): initial rotations
    weight = {(f1, f2): len(b1) for f1, f2, b1, _, _, _ in edges}
    root = min(f for e in weight for f in e)
    R_abs: dict[int, np.ndarray] = {root: np.eye(3)}  # world-to-camera rotations
    while True:
        cand = [(w, a, b) for (a, b), w in weight.items() if (a in R_abs) != (b in R_abs)]
        if not cand:
            break
        _, a, b = max(cand)
        if a in R_abs:
            R_abs[b] = rel[(a, b)] @ R_abs[a]
        else:
            R_abs[a] = rel[(a, b)].T @ R_abs[b]
    frames = sorted(R_abs)
    pos = {f: k for k, f in enumerate(frames)}
    sub = []
    for f1, f2, b1, b2, x2, x1 in edges:
        if f1 in pos and f2 in pos:
            take = rng.permutation(len(b1))[:max_matches]
            sub.append((pos[f1], pos[f2], b1[take], b2[take], x2[take], x1[take]))
    x0 = np.concatenate([Rotation.from_matrix(R_abs[f]).as_rotvec() for f in frames[1:]] or [np.zeros(0)])

    def rotations(x: np.ndarray) -> list[np.ndarray]:
        return [np.eye(3)] + list(Rotation.from_rotvec(x.reshape(-1, 3)).as_matrix()) if len(x) else [np.eye(3)]

    def residuals(x: np.ndarray, data) -> np.ndarray:
        Rs = rotations(x)
        out = []
        for a, b, b1, b2, x2, x1 in data:
            R = Rs[b] @ Rs[a].T
            out.append((_project(K, b1 @ R.T) - x2).ravel())  # i -> j
            out.append((_project(K, b2 @ R) - x1).ravel())  # j -> i
        return np.concatenate(out)

    if len(x0):
        x = least_squares(residuals, x0, args=(sub,), loss="soft_l1", f_scale=1.0, method="trf").x
    else:
        x = x0
    # the acceptance test runs on ALL verified matches of the connected frames, outliers of the rotation included
    full = [(pos[f1], pos[f2], b1, b2, x2, x1) for f1, f2, b1, b2, x2, x1 in all_edges if f1 in pos and f2 in pos]
    r = residuals(x, full).reshape(-1, 2)
    px = np.linalg.norm(r, axis=1) / upscale
    med, p90 = float(np.median(px)), float(np.percentile(px, 90))
    inlier_err = float(px[px <= inlier_px].mean()) if (px <= inlier_px).any() else float("nan")
    c2w = np.full((n, 4, 4), np.nan)
    registered = np.zeros(n, dtype=bool)
    for f, R in zip(frames, rotations(x)):
        c2w[f] = np.eye(4)
        c2w[f, :3, :3] = R.T  # every camera at the origin
        registered[f] = True
    k = int(registered.sum())
    if med > ROTATION_MAX_MEDIAN_PX or p90 > ROTATION_MAX_P90_PX:
        return _failed(n, f"rejected: a pure rotation leaves residuals of {med:.2f} px (median) / {p90:.2f} px "
                       "(90th percentile): the camera moved", mean_reprojection_error=inlier_err, **info)
    reason = "" if k == n else f"{n - k} of {n} frames not connected by verified matches"
    return PoseRecovery(c2w, registered, n, k, n_reconstructions=1, n_points3d=0,
                        mean_reprojection_error=inlier_err, reason=reason, **info)
