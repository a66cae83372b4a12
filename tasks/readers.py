"""Readers of what several steps, reports, tools and benchmarks read back from a store: which scene a user means
(``resolve_scene``: one resolver of scene ids, id prefixes and photo names for every tool), the manifest, and of a
scene the camera path of its clips (one definition of frames, poses, intrinsics and size), the scene centre, the
current pose, and the stored Gaussians and the fit's views."""

from __future__ import annotations

import difflib
import json
from dataclasses import dataclass
from pathlib import PurePath
from typing import Literal

import numpy as np
import pyarrow as pa
import torch

from navcrafter.models.camera.cameras import Intrinsics, estimated_clip_cameras
from navcrafter.models.gaussians.model import GaussianModel
from navcrafter.models.gaussians.recipe import resize_image
from navcrafter.models.gaussians.train import TrainView
from navcrafter.models.planning.planners import scene_centre
from navcrafter.models.simulation import simulation_label
from navcrafter.schemas.config import RUN_CONFIG_FILE, RunConfig, StoredRunConfig
from navcrafter.schemas.layout import (
    EXPORT,
    FIT,
    GEOMETRY,
    INGEST,
    LIFT,
    PLAN,
    REFINE,
    SYNTHESIZE,
    StepSpec,
    scene_group,
)
from navcrafter.schemas.store import SceneStore, Store
from navcrafter.tasks.backends import run_label
from navcrafter.tasks.common import logger


# --------------------------------------------------------------------------------------------------
# The store's scenes, and which one a user means
# --------------------------------------------------------------------------------------------------
class SceneNotFound(ValueError):
    """A scene id, id prefix or photo name that names no single scene of a store (the message names the input,
    the scenes it could mean and the fix)."""


def read_manifest(store: Store) -> pa.Table:
    """The manifest's latest row per source image (empty for scenes run outside a flow)."""
    return store.tables.latest("manifest", key=("source",), order="updated_at")


def scene_sources(store: Store) -> dict[str, list[str]]:
    """Source paths of each scene id of a store: the manifest's rows, else the ingest step's ``source``."""
    out: dict[str, list[str]] = {sid: [] for sid in store.scene_ids()}
    for r in read_manifest(store).to_pylist():
        if r.get("scene_id") in out and r.get("source") and r["source"] not in out[r["scene_id"]]:
            out[r["scene_id"]].append(r["source"])
    for sid, sources in out.items():
        if not sources:
            src = store.scene(sid).status(INGEST).attrs.get("source")
            if src:
                sources.append(src)
    return out


def scene_choices(store: Store, sources: dict[str, list[str]] | None = None) -> dict[str, str]:
    """``<photo file name> (<id[:12]>)`` -> scene id for every scene of a store, sorted by that name (the viewer's
    dropdown, and how the resolver's errors list scenes)."""
    labels = {}
    for sid, srcs in (scene_sources(store) if sources is None else sources).items():
        names = ", ".join(dict.fromkeys(PurePath(s).name for s in srcs)) or "unknown source"
        labels[f"{names} ({sid[:12]})"] = sid
    return dict(sorted(labels.items()))


def _listing(labels: list[str], limit: int = 6) -> str:
    return ", ".join(labels[:limit]) + (f" and {len(labels) - limit} more" if len(labels) > limit else "")


def resolve_scene(store: Store, scene: str | None, default: Literal["only", "first"] = "only",
                  option: str = "SCENE") -> str:
    """The id of the scene of ``store`` that ``scene`` names: the whole id, a unique id prefix, or the photo it was
    explored from (its path, file name or file stem, as the manifest or the ingest step recorded it). Every tool
    that takes a scene from a user (``navcrafter view``, ``export``, ``render``) resolves it here.

    ``scene=None``: ``default="only"`` takes the store's only scene (an error when it holds several),
    ``default="first"`` the first in ``scene_choices`` order. ``option`` is how the user gives a scene (the CLI
    argument or option), named in the fix. Raises ``SceneNotFound`` naming the input, the scenes it matches (or,
    when none, the closest names and the store's scenes) and how to give one."""
    uri = store.uri
    sources = scene_sources(store)
    if not sources:
        raise SceneNotFound(f"{uri} has no scenes yet; run `navcrafter explore PHOTOS --store {uri}` first")
    choices = scene_choices(store, sources)
    label_of = {sid: lab for lab, sid in choices.items()}
    hint = f"`navcrafter status {uri}` lists them"
    if scene is None:
        if default == "first" or len(sources) == 1:
            return next(iter(choices.values()))
        raise SceneNotFound(f"{uri} holds {len(sources)} scenes; choose one with {option} (its id, a unique id "
                            f"prefix or its photo's file name): {_listing(list(choices))} ({hint})")
    if scene in sources:
        return scene
    matches = [sid for sid in sources if scene and sid.startswith(scene)]
    if not matches:
        matches = [sid for sid, srcs in sources.items()
                   if any(scene in (s, PurePath(s).name, PurePath(s).stem) for s in srcs)]
    if len(matches) == 1:
        return matches[0]
    if matches:
        raise SceneNotFound(f"{option} {scene!r} matches {len(matches)} scenes of {uri} "
                            f"({_listing([label_of[m] for m in sorted(matches)])}); give more characters of the id "
                            "or the photo's file name")
    names = {PurePath(s).name: sid for sid, srcs in sources.items() for s in srcs}
    close = difflib.get_close_matches(scene, list(names) + list(sources), n=3, cutoff=0.75)
    near = list(dict.fromkeys(label_of[names.get(c, c)] for c in close))
    listed = (f"did you mean {_listing(near)}?" if near else f"its scenes: {_listing(list(choices))}")
    raise SceneNotFound(f"{option} {scene!r} names no scene of {uri} (neither a scene id, an id prefix nor the "
                        f"file name of an explored photo); {listed} ({hint})")


@dataclass(frozen=True)
class CameraPath:
    """Frames of a scene's clips at the cameras they were synthesized for (the planned poses): per frame its
    iteration ``k`` and index ``i`` in clip k, OpenCV c2w [F, 4, 4] and K [F, 3, 3] at ``width`` x ``height``.

    Repeated first frames: iteration k >= 2 starts at the last pose of clip k-1, and its clip is conditioned on
    clip k-1's last frame (``tasks/synthesize.py``), which an I2V model reproduces as frame 0. So frame 0 of
    clip k >= 2 is a second view of the camera of (k-1, T-1), a reproduction rather than a new view.
    ``distinct()`` drops the repeat and keeps the first occurrence (the frame clip k was conditioned on), so each
    camera of the path counts once; the lift step never selects frame 0 (``lifting.select_views``), and the fit
    trains on and holds out only distinct frames (its ``frame_ref``, which ``load_fit_views`` reads back)."""

    iteration: np.ndarray
    frame: np.ndarray
    c2w: np.ndarray
    K: np.ndarray
    width: int
    height: int

    def __len__(self) -> int:
        return len(self.c2w)

    @property
    def refs(self) -> list[tuple[int, int]]:
        """(k, i) of every frame."""
        return [(int(k), int(i)) for k, i in zip(self.iteration, self.frame)]

    def select(self, mask_or_index) -> CameraPath:
        return CameraPath(self.iteration[mask_or_index], self.frame[mask_or_index], self.c2w[mask_or_index],
                          self.K[mask_or_index], self.width, self.height)

    def distinct(self) -> CameraPath:
        """Without frame 0 of clips k >= 2: it reproduces the last frame of clip k-1 at the same pose (kept)."""
        return self.select((self.iteration == 1) | (self.frame > 0))

    def clip(self, k: int) -> CameraPath:
        return self.select(self.iteration == k)

    def intrinsics(self, f: int) -> Intrinsics:
        return Intrinsics.from_matrix(self.K[f], self.width, self.height)


def stored_run_config(scene: SceneStore) -> StoredRunConfig | None:
    """The run configuration the scene's latest run stored before its first step (``schemas.config
    .StoredRunConfig``), or None for a scene written before runs stored it."""
    rel = f"{scene_group(scene.scene_id)}/{RUN_CONFIG_FILE}"
    try:
        data = scene.store.read_bytes(rel)
    except FileNotFoundError:
        return None
    return StoredRunConfig.model_validate_json(data)


def scene_run_config(scene: SceneStore, iterations: int | None = None) -> RunConfig:
    """The config the scene's latest run ran with (stored with the scene). A scene written before runs stored their
    config (before navcrafter stored ``run_config.json``) falls back, with a warning, to the defaults with the
    synthesis size of its ingested working image and ``iterations`` (when given) as a reconstruction."""
    stored = stored_run_config(scene)
    if stored is not None:
        return stored.config
    logger().warning(f"scene {scene.scene_id[:12]}: written before runs stored their config ({RUN_CONFIG_FILE}); "
                     "the default config with the scene's image size is assumed (rerun `navcrafter explore` with "
                     "the same config to store it: nothing is recomputed)")
    width, height = scene.require_complete(INGEST).attrs["work_size"]
    base = RunConfig()
    synthesis = base.synthesis.model_copy(update={"width": int(width), "height": int(height)})
    return base.model_copy(update={"synthesis": synthesis,
                                   **({} if iterations is None else {"iterations": int(iterations)})})


def export_record(scene: SceneStore) -> dict:
    """The export step's ``trajectory.json`` (the frames with their iterations, backend, label of the run); ``{}``
    before the export completed or when it wrote none."""
    st = scene.status(EXPORT)
    doc = st.attrs.get("files", {}).get("trajectory.json") if st.complete else None
    return json.loads(scene.store.read_bytes(doc["path"])) if doc else {}


def truth_scene(scene: SceneStore) -> dict | None:
    """The ``scene`` spec of a demo photo's hidden ground truth (ingest's ``simulation_truth``: kind, seed or the
    scanned world's name), or None for any other image or before ingest completed."""
    st = scene.status(INGEST)
    record = st.attrs.get("simulation_truth") if st.complete else None
    spec = record.get("scene") if isinstance(record, dict) else None
    return spec if isinstance(spec, dict) else None


def scene_run_label(scene: SceneStore, config: RunConfig) -> str | None:
    """``run_label`` of ``config`` for this scene (a scanned world's simulation label names the scan)."""
    return run_label(config, truth_scene(scene))


def scene_label(scene: SceneStore) -> str | None:
    """The label every output of the scene's run carries (SIMULATION, RANDOM WEIGHTS, CAMERA CONTROL UNTRAINED;
    ``tasks.backends.run_label``), or None: the one its export recorded, else the stored run config's, else (a scene
    written before runs stored their config) the simulation's when its steps recorded that backend."""
    try:
        label = export_record(scene).get("label")
    except (OSError, ValueError):
        label = None
    if label:
        return label
    stored = stored_run_config(scene)
    if stored is not None:
        return scene_run_label(scene, stored.config)
    for spec in (INGEST, GEOMETRY, FIT):
        if scene.status(spec).attrs.get("backend") == "simulation":
            return simulation_label(truth_scene(scene))
    return None


def camera_path(scene: SceneStore, config: RunConfig, iterations: int | None = None,
                cameras: str = "planned") -> CameraPath:
    """Every frame of clips 1..``iterations`` (default ``config.iterations``; with the repeated first frames,
    which ``.distinct()`` drops), at the synthesis size.

    ``cameras``: ``"planned"``, the poses the frames were requested at (the plan steps' trajectories);
    ``"estimated"``, the geometry model's cameras (the paper fits 3DGS on these): the lift step's aligned pose on
    the frames it ran the geometry model on, and on the others the planned pose corrected by the estimate's
    deviation from the plan, interpolated between the nearest estimated frames (frame 0 of a clip is where the
    previous clip's estimate ended, or the input camera, so its deviation is zero)."""
    if cameras not in ("planned", "estimated"):
        raise ValueError(f"cameras must be 'planned' or 'estimated', got {cameras!r}")
    iterations = config.iterations if iterations is None else iterations
    ks, idx, c2w, K = [], [], [], []
    for k in range(1, iterations + 1):
        traj, Kk = scene.read(PLAN, k, "trajectory"), scene.read(PLAN, k, "K")
        traj = np.asarray(traj, dtype=np.float64)
        if cameras == "estimated":
            traj = estimated_clip_cameras(traj, scene.read(LIFT, k, "view_index"), scene.read(LIFT, k, "c2w"))
        ks += [k] * len(traj)
        idx += list(range(len(traj)))
        c2w.append(traj)
        K.append(np.repeat(np.asarray(Kk, dtype=np.float64)[None], len(traj), axis=0))
    height, width = config.synthesis.height, config.synthesis.width
    return CameraPath(np.asarray(ks, dtype=np.int64), np.asarray(idx, dtype=np.int64),
                      np.concatenate(c2w) if c2w else np.zeros((0, 4, 4)),
                      np.concatenate(K) if K else np.zeros((0, 3, 3)), int(width), int(height))


def frame_truth(scene: SceneStore, k: int, frames: np.ndarray) -> tuple[np.ndarray, list[np.ndarray | None]]:
    """The simulation's hidden truth of frames of clip k (the synthesize step's ``true_c2w`` / ``true_depth``):
    the hints of the simulated Geometry and MonoDepth roles, which learned backends ignore. A store written
    before the truth was kept gives the planned poses and no depth."""
    frames = np.asarray(frames, dtype=np.int64)
    c2w = true_cameras(scene, k)[frames]
    if scene.has(SYNTHESIZE, k, "true_depth"):
        return c2w, list(scene.read_rows(SYNTHESIZE, k, "true_depth", frames))
    return c2w, [None] * len(frames)


def true_cameras(scene: SceneStore, k: int) -> np.ndarray:
    """World c2w ``[T, 4, 4]`` where each frame of clip k was really taken (the synthesize step's ``true_c2w``,
    simulation only); the planned trajectory for a clip stored without it."""
    name = "true_c2w" if scene.has(SYNTHESIZE, k, "true_c2w") else None
    return np.asarray(scene.read(SYNTHESIZE, k, name) if name else scene.read(PLAN, k, "trajectory"),
                      dtype=np.float64)


def input_pose(scene: SceneStore) -> np.ndarray:
    """World c2w of the input camera (``iter_0/geometry``: the identity, which defines the world frame)."""
    return scene.read(GEOMETRY, None, "c2w")


def current_pose(scene: SceneStore, k: int) -> np.ndarray:
    """Where iteration k starts: the input camera, then the geometry model's estimate of the camera of clip
    k-1's last frame (``iter_{k-1}/lift``, which always lifts the last frame): the next clip is conditioned on that
    frame, so its motion is planned from where the frame is believed to be, not from where it was requested."""
    if k == 1:
        return np.eye(4)
    T = len(scene.read(PLAN, k - 1, "trajectory"))
    views = np.asarray(scene.read(LIFT, k - 1, "view_index"))
    last = np.flatnonzero(views == T - 1)
    if len(last) == 0:
        raise ValueError(f"iter_{k - 1}/lift did not lift the clip's last frame ({T - 1}); cannot start iteration {k}")
    return np.asarray(scene.read(LIFT, k - 1, "c2w")[int(last[0])], dtype=np.float64)


def stored_scene_centre(scene: SceneStore, config: RunConfig) -> np.ndarray:
    """The scene centre ``o`` of a scene, from its initial geometry."""
    geo = scene.read_all(GEOMETRY)
    return scene_centre(geo["depth"], geo["confidence"], config.plan.centre_depth_quantile)


def load_gaussians(scene: SceneStore, step: StepSpec = FIT) -> GaussianModel:
    """The Gaussians a step stored (the fit's ``gaussians`` group by default; the refine step's ``renders``);
    the group must be complete."""
    scene.require_complete(step)
    arrays = scene.read_all(step)
    return GaussianModel(**{k: torch.from_numpy(np.ascontiguousarray(arrays[k])) for k in
                            ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")})


def load_refined_gaussians(scene: SceneStore) -> GaussianModel:
    """The refined model of a scene (its ``renders`` group must be complete)."""
    return load_gaussians(scene, REFINE)


def load_final_gaussians(scene: SceneStore) -> tuple[GaussianModel, StepSpec]:
    """A scene's final Gaussians as its store holds them, and the step that stored them: the refine step's when it
    completed, else the fit's (which must be complete). What the tools show and render (``navcrafter view``,
    ``render``)."""
    step = REFINE if scene.status(REFINE).complete else FIT
    return load_gaussians(scene, step), step


def load_fit_views(scene: SceneStore) -> tuple[list[TrainView], list[TrainView]]:
    """The fit's training and held-out views, rebuilt from its group (frames from the synthesize steps,
    resized as the fit did; calibrated depth targets of the training views)."""
    scene.require_complete(FIT)
    g = scene.read_all(FIT)
    w, h = scene.status(FIT).attrs["resolution"]
    frames: dict[int, np.ndarray] = {}
    train, test = [], []
    for f, (k, i) in enumerate(np.asarray(g["frame_ref"])):
        if int(k) not in frames:
            frames[int(k)] = scene.read(SYNTHESIZE, int(k), "frames")
        img = resize_image(frames[int(k)][int(i)], h, w).astype(np.float32) / 255.0
        d = g["depth_targets"][f]
        view = TrainView(torch.from_numpy(img), torch.as_tensor(g["c2w"][f], dtype=torch.float32),
                         torch.as_tensor(g["K"][f], dtype=torch.float32),
                         torch.from_numpy(np.ascontiguousarray(d)) if (d > 0).any() else None)
        if g["holdout"][f]:
            test.append(view)
        elif g["train"][f]:
            train.append(view)
    return train, test
