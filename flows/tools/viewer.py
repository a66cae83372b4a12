"""The 3D viewer of explored scenes (``navcrafter view``), on viser (https://viser.studio).

Plain functions over a store and a ``viser.ViserServer`` (no browser needed to call or test them):

* the scenes of a store by id and source name are ``tasks.readers.scene_choices`` / ``resolve_scene`` (the one
  resolver of every tool);
* ``read_scene``: what a scene holds (``SceneData``): the input photo, per iteration the plan (trajectory,
  candidates, the collision detector G's verdicts), the estimated cameras of the lift, the synthesized frames,
  the fused clouds (read when first shown) and the fitted Gaussians when the fit ran;
* ``build_scene``: the scene's nodes under ``/scene`` (``SceneView``, which shows an iteration or a frame);
* ``build_viewer``: the GUI (scene dropdown, layer toggles, iteration and frame sliders) over ``build_scene``.

Conventions. The store's cameras are OpenCV camera-to-world (x right, y down, z forward) in the world of the
input camera (the identity). viser's frustums follow the same OpenCV camera convention (they look along +z,
``fov`` vertical, ``aspect`` width / height) and a node's ``wxyz`` / ``position`` are its rotation and
translation to the parent frame, so a c2w maps directly: ``wxyz = quat(R)``, ``position = t``. The world's up
is the input camera's -y (``set_up_direction("-y")``).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from navcrafter.models.camera.cameras import matrix_to_quat, quat_wxyz_to_matrix
from navcrafter.models.gaussians.sh import SH_C0
from navcrafter.schemas.layout import FIT, GEOMETRY, INGEST, LIFT, PLAN, REFINE, SYNTHESIZE
from navcrafter.schemas.store import SceneStore, Store
from navcrafter.tasks.common import load_cloud
from navcrafter.tasks.readers import load_final_gaussians, resolve_scene, scene_choices, scene_label, scene_sources

# RGB of each kind of camera
COLOURS = {
    "input": (20, 20, 20),
    "planned": (40, 110, 255),
    "estimated": (255, 140, 0),
    "accepted": (40, 170, 70),
    "rejected": (220, 30, 30),
    "chosen": (150, 0, 200),
    "frame": (230, 0, 160),
    "initial": (150, 190, 255),
}
MAX_CLOUD_POINTS = 400_000  # per cloud sent to the browser (a random subset beyond, fixed seed)
NO_FIT = "this scene has no fit yet (fit.enabled was off or the fit has not run): showing the fused cloud only"
LAYERS = ("gaussians", "cloud", "planned", "estimated", "candidates", "input")


# --------------------------------------------------------------------------------------------------
# What a scene holds
# --------------------------------------------------------------------------------------------------
@dataclass
class Iteration:
    """One iteration k of a scene: its plan, the lift's estimated cameras and the synthesized frames (None
    where the step has not completed)."""

    k: int
    trajectory: np.ndarray  # [T, 4, 4] planned c2w of every frame
    K: np.ndarray  # [3, 3]
    candidates: np.ndarray  # [C, 4, 4]
    collides: np.ndarray  # [C] bool: rejected by the collision detector G (all False when not stored)
    scores: np.ndarray | None  # [C]
    chosen: int | None
    strategy: str
    initial_trajectory: np.ndarray | None  # [T, 4, 4] before the collision optimisation
    estimated: np.ndarray | None = None  # [S, 4, 4] the lift's aligned poses
    estimated_K: np.ndarray | None = None  # [S, 3, 3]
    view_index: np.ndarray | None = None  # [S] frame of each estimate
    frames: np.ndarray | None = None  # [T, H, W, 3] uint8

    @property
    def rejected(self) -> np.ndarray:
        return np.flatnonzero(self.collides)

    @property
    def accepted(self) -> np.ndarray:
        return np.flatnonzero(~self.collides)


@dataclass
class SceneData:
    scene: SceneStore
    scene_id: str
    source: str
    label: str | None
    backend: str | None
    image: np.ndarray | None  # the input photo
    work_image: np.ndarray | None
    K0: np.ndarray | None  # intrinsics of the working image
    width: int
    height: int
    iterations: list[Iteration]
    cloud_iterations: list[int]  # k with a stored cloud (0 = the initial geometry)
    gaussians: Any | None = None  # GaussianModel of the fit (refined when the refine step ran)
    gaussians_note: str = ""
    _clouds: dict[int, Any] = field(default_factory=dict, repr=False)

    def cloud(self, k: int):
        """The fused cloud after iteration k (``tasks.common.load_cloud``), read once."""

        if k not in self._clouds:
            self._clouds[k] = load_cloud(self.scene, k)
        return self._clouds[k]

    @property
    def frame_refs(self) -> list[tuple[int, int]]:
        """(k, i) of every synthesized frame, clip after clip."""
        return [(it.k, i) for it in self.iterations if it.frames is not None for i in range(len(it.frames))]


def read_scene(store: Store, scene_id: str) -> SceneData:
    """Everything the viewer shows of a scene, from its completed steps (a partly explored scene shows what it
    has). The clouds are read when first shown (``SceneData.cloud``)."""
    scene = store.scene(scene_id)
    ingest = scene.status(INGEST)
    image = work = None
    width = height = 0
    if ingest.complete:
        image, work = scene.read(INGEST, None, "image"), scene.read(INGEST, None, "work_image")
        width, height = (int(v) for v in ingest.attrs["work_size"])
    sources = scene_sources(store).get(scene_id) or [ingest.attrs.get("source", "")]
    geo = scene.status(GEOMETRY)
    K0 = scene.read(GEOMETRY, None, "K") if geo.complete else None
    iterations = []
    k = 1
    while scene.status(PLAN, k).complete:
        st = scene.status(PLAN, k)
        plan = scene.read_all(PLAN, k)
        C = len(plan["candidates"])
        chosen = st.attrs.get("chosen")
        it = Iteration(k, plan["trajectory"], plan["K"], plan["candidates"],
                       np.asarray(plan.get("candidate_collides", np.zeros(C, dtype=bool)), dtype=bool),
                       plan.get("candidate_scores"), None if chosen is None else int(chosen),
                       str(st.attrs.get("strategy", "")), plan.get("initial_trajectory"))
        if scene.status(LIFT, k).complete:
            it.estimated, it.estimated_K = scene.read(LIFT, k, "c2w"), scene.read(LIFT, k, "K")
            it.view_index = scene.read(LIFT, k, "view_index")
        if scene.status(SYNTHESIZE, k).complete:
            it.frames = scene.read(SYNTHESIZE, k, "frames")
        iterations.append(it)
        k += 1
    clouds = ([0] if geo.complete else []) + [it.k for it in iterations if it.estimated is not None]
    data = SceneData(scene, scene_id, sources[0] if sources else "", scene_label(scene), ingest.attrs.get("backend"),
                     image, work, K0, width, height, iterations, clouds)
    if scene.status(FIT).complete:
        data.gaussians, step = load_final_gaussians(scene)
        refined = step == REFINE
        a = scene.status(step).attrs
        psnr = a.get("psnr")
        data.gaussians_note = (f"{len(data.gaussians)} Gaussians{' (refined)' if refined else ''}"
                               + (f", held-out PSNR {psnr:.2f} dB" if isinstance(psnr, (int, float)) else ""))
    else:
        data.gaussians_note = NO_FIT
    return data


# --------------------------------------------------------------------------------------------------
# Conversions to viser's arguments
# --------------------------------------------------------------------------------------------------
def pose_to_viser(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(wxyz, position)`` of a node placed at an OpenCV c2w (viser's cameras are OpenCV too)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    return matrix_to_quat(c2w[:3, :3]), c2w[:3, 3].copy()


def frustum_fov(K: np.ndarray, height: int) -> float:
    """Vertical field of view (radians) of intrinsics K for an image ``height`` pixels tall."""
    return float(2.0 * np.arctan2(0.5 * height, float(K[1, 1])))


def gaussian_splat_arrays(model) -> dict[str, np.ndarray]:
    """``add_gaussian_splats``'s arrays from a ``GaussianModel`` (3DGS's raw parameters): centres, covariances
    ``R diag(s^2) R^T`` (``s = exp(log_scales)``, R from the normalised quaternion), RGB from the degree-0 SH
    term (``0.5 + C0 dc``, view-independent), opacities ``sigmoid(logit)`` as ``[N, 1]``."""

    def arr(t) -> np.ndarray:
        return t.detach().cpu().numpy().astype(np.float64) if hasattr(t, "detach") else np.asarray(t, np.float64)

    R = quat_wxyz_to_matrix(arr(model.quats))
    s2 = np.exp(2.0 * arr(model.log_scales))
    cov = np.einsum("nij,nj,nkj->nik", R, s2, R)
    rgb = np.clip(0.5 + SH_C0 * arr(model.sh_dc), 0.0, 1.0)
    opacity = 1.0 / (1.0 + np.exp(-arr(model.opacity_logits)))
    return {"centers": arr(model.means).astype(np.float32), "covariances": cov.astype(np.float32),
            "rgbs": rgb.astype(np.float32), "opacities": opacity[:, None].astype(np.float32)}


def scene_extent(points: np.ndarray) -> float:
    """A length for sizing frustums: the median distance of the cloud from the input camera (1 if empty)."""
    if len(points) == 0:
        return 1.0
    d = float(np.median(np.linalg.norm(points, axis=1)))
    return d if np.isfinite(d) and d > 0 else 1.0


def point_size(points: np.ndarray, sample: int = 2000) -> float:
    """A point size that closes the gaps of the cloud: its median nearest-neighbour spacing."""
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return 0.01
    rng = np.random.default_rng(0)
    probe = points[rng.choice(len(points), min(sample, len(points)), replace=False)]
    dist, _ = cKDTree(points).query(probe, k=2)
    d = float(np.median(dist[:, 1]))
    return max(d * 1.5, 1e-4) if np.isfinite(d) else 0.01


def subsample(points: np.ndarray, colors: np.ndarray, limit: int = MAX_CLOUD_POINTS):
    if len(points) <= limit:
        return points, colors
    idx = np.sort(np.random.default_rng(0).choice(len(points), limit, replace=False))
    return points[idx], colors[idx]


def thumbnail(image: np.ndarray, max_side: int = 320) -> np.ndarray:
    """The image scaled down so its longer side is at most ``max_side`` (for the GUI and frustum images)."""
    from PIL import Image

    h, w = image.shape[:2]
    if max(h, w) <= max_side:
        return image
    s = max_side / max(h, w)
    return np.asarray(Image.fromarray(image).resize((max(1, round(w * s)), max(1, round(h * s))), Image.BILINEAR))


def path_segments(c2w: np.ndarray) -> np.ndarray:
    """Line segments ``[T-1, 2, 3]`` joining the camera centres of a trajectory."""
    x = np.asarray(c2w)[:, :3, 3]
    return np.stack([x[:-1], x[1:]], axis=1).astype(np.float32)


# --------------------------------------------------------------------------------------------------
# The scene's nodes
# --------------------------------------------------------------------------------------------------
ROOT = "/scene"


@dataclass
class SceneView:
    """The nodes of one scene on a server, by name (``nodes``), and what shows them."""

    server: Any
    data: SceneData
    nodes: dict[str, Any]
    frustum_scale: float
    point_size: float
    layers: dict[str, bool] = field(default_factory=lambda: dict.fromkeys(LAYERS, True))
    iteration: int = 0
    cumulative: bool = True  # cameras of iterations 1..k, else of k only
    frame: int | None = None
    _lock: threading.RLock = field(default_factory=threading.RLock, repr=False)

    def _add(self, name: str, method: str, *args, **kw):
        handle = getattr(self.server.scene, method)(name, *args, **kw)
        self.nodes[name] = handle
        return handle

    # -- what is shown ------------------------------------------------------------------------------
    def cloud_node(self, k: int):
        """The node of the cloud after iteration k, added when first asked for."""
        name = f"{ROOT}/cloud/iter_{k}"
        if name not in self.nodes:
            cloud = self.data.cloud(k)
            pts, cols = subsample(cloud.points, cloud.colors)
            self._add(name, "add_point_cloud", pts.astype(np.float32), cols, point_size=self.point_size,
                      point_shape="rounded", point_shading="flat", precision="float32", visible=False)
        return self.nodes[name]

    def show_iteration(self, k: int, cumulative: bool | None = None) -> None:
        """The cloud after iteration k (the latest stored one at or before k) and the cameras of iterations 1..k
        (or k only, ``cumulative=False``)."""
        with self._lock:
            self.iteration = int(k)
            if cumulative is not None:
                self.cumulative = bool(cumulative)
            self._refresh()

    def set_layer(self, layer: str, visible: bool) -> None:
        if layer not in LAYERS:
            raise ValueError(f"unknown layer {layer!r}; layers: {', '.join(LAYERS)}")
        with self._lock:
            self.layers[layer] = bool(visible)
            self._refresh()

    def shown_cloud(self) -> int | None:
        """k of the cloud shown for the current iteration: the latest stored at or before it."""
        ks = [c for c in self.data.cloud_iterations if c <= self.iteration]
        return ks[-1] if ks else None

    def _refresh(self) -> None:
        k, lay = self.iteration, self.layers
        want = self.shown_cloud() if lay["cloud"] else None
        if want is not None:
            self.cloud_node(want)
        for name, handle in self.nodes.items():
            if name.startswith(f"{ROOT}/cloud/iter_"):
                handle.visible = name == f"{ROOT}/cloud/iter_{want}"
        if f"{ROOT}/gaussians" in self.nodes:
            self.nodes[f"{ROOT}/gaussians"].visible = lay["gaussians"]
        if f"{ROOT}/input" in self.nodes:
            self.nodes[f"{ROOT}/input"].visible = lay["input"]
        for it in self.data.iterations:
            shown = it.k == k or (self.cumulative and it.k < k)
            self.nodes[f"{ROOT}/iter_{it.k}"].visible = shown
            for layer in ("planned", "estimated", "candidates"):
                node = self.nodes.get(f"{ROOT}/iter_{it.k}/{layer}")
                if node is not None:
                    node.visible = lay[layer]

    def show_frame(self, f: int | None) -> np.ndarray | None:
        """Highlight frame f of the video (index into ``data.frame_refs``): a frustum at its planned camera
        carrying the frame; ``None`` removes it. Returns the frame."""
        with self._lock:
            name = f"{ROOT}/video/current"
            refs = self.data.frame_refs
            if f is None or not refs:
                if name in self.nodes:
                    self.nodes.pop(name).remove()
                self.frame = None
                return None
            f = int(np.clip(f, 0, len(refs) - 1))
            k, i = refs[f]
            it = self.data.iterations[k - 1]
            wxyz, pos = pose_to_viser(it.trajectory[i])
            frame = it.frames[i]
            h, w = frame.shape[:2]
            self._add(name, "add_camera_frustum", fov=frustum_fov(it.K, self.data.height or h),
                      aspect=w / h, scale=1.6 * self.frustum_scale, thickness=0.05 * self.frustum_scale,
                      color=COLOURS["frame"], image=thumbnail(frame, 256), wxyz=wxyz, position=pos)
            self.frame = f
            return frame

    def remove(self) -> None:
        """Take the scene off the server (its root node and everything under it)."""
        with self._lock:
            root = self.nodes.get(ROOT)
            if root is not None:
                root.remove()
            self.nodes.clear()


def _frustum(view: SceneView, name: str, c2w: np.ndarray, K: np.ndarray, colour: str, scale: float = 1.0,
             image: np.ndarray | None = None) -> None:
    data = view.data
    wxyz, pos = pose_to_viser(c2w)
    h = data.height or (image.shape[0] if image is not None else 1)
    w = data.width or (image.shape[1] if image is not None else 1)
    view._add(name, "add_camera_frustum", fov=frustum_fov(K, h), aspect=w / h, scale=scale * view.frustum_scale,
              thickness=0.03 * scale * view.frustum_scale, color=COLOURS[colour], image=image, wxyz=wxyz,
              position=pos)


def build_scene(server, store_uri: str | Store, scene_id: str, data: SceneData | None = None) -> SceneView:
    """Add a scene's nodes to a viser server under ``/scene`` (any previous ones replaced):

    * ``/scene/gaussians``: the fitted Gaussians (when the fit ran);
    * ``/scene/cloud/iter_<k>``: the fused cloud after iteration k (added when first shown; the latest);
    * ``/scene/input``: the input camera with the working image;
    * ``/scene/iter_<k>/planned/f<i>``, ``.../planned/path`` (and ``initial_path`` when the collision
      optimisation moved it): the planned cameras of clip k;
    * ``/scene/iter_<k>/estimated/v<j>``: the lift's estimated cameras;
    * ``/scene/iter_<k>/candidates/{accepted,rejected}_<c>``: the plan's candidates, rejected = by G;
      the chosen one ``chosen_<c>``;
    * ``/scene/video/current``: the highlighted video frame (``SceneView.show_frame``).

    Shows the last iteration. ``store_uri``: a URI or an open ``Store``."""
    store = store_uri if isinstance(store_uri, Store) else Store(store_uri, create=False)
    data = data or read_scene(store, scene_id)
    last = data.cloud_iterations[-1] if data.cloud_iterations else None
    pts = data.cloud(last).points if last is not None else np.zeros((0, 3), np.float32)
    extent = scene_extent(pts)
    view = SceneView(server, data, {}, frustum_scale=0.06 * extent, point_size=point_size(pts))
    server.scene.set_up_direction("-y")
    server.scene.remove_by_name(ROOT)  # a scene shown before
    with server.atomic():
        view._add(ROOT, "add_frame", show_axes=False)
        if data.gaussians is not None:
            view._add(f"{ROOT}/gaussians", "add_gaussian_splats", **gaussian_splat_arrays(data.gaussians))
        if data.K0 is not None:
            _frustum(view, f"{ROOT}/input", np.eye(4), data.K0, "input", 1.6,
                     None if data.work_image is None else thumbnail(data.work_image, 256))
        for it in data.iterations:
            base = f"{ROOT}/iter_{it.k}"
            view._add(base, "add_frame", show_axes=False)
            view._add(f"{base}/planned", "add_frame", show_axes=False)
            for i, c2w in enumerate(it.trajectory):
                _frustum(view, f"{base}/planned/f{i:03d}", c2w, it.K, "planned", 0.7)
            view._add(f"{base}/planned/path", "add_line_segments", path_segments(it.trajectory),
                      COLOURS["planned"], thickness=0.02 * view.frustum_scale)
            if it.initial_trajectory is not None and not np.allclose(it.initial_trajectory, it.trajectory):
                view._add(f"{base}/planned/initial_path", "add_line_segments", path_segments(it.initial_trajectory),
                          COLOURS["initial"], thickness=0.015 * view.frustum_scale)
            if it.estimated is not None:
                view._add(f"{base}/estimated", "add_frame", show_axes=False)
                for j, c2w in enumerate(it.estimated):
                    _frustum(view, f"{base}/estimated/v{j:03d}", c2w, it.estimated_K[j], "estimated", 0.85)
            view._add(f"{base}/candidates", "add_frame", show_axes=False)
            for c, c2w in enumerate(it.candidates):
                kind = "chosen" if c == it.chosen else "rejected" if it.collides[c] else "accepted"
                _frustum(view, f"{base}/candidates/{kind}_{c:03d}", c2w, it.K, kind, 1.2 if kind == "chosen" else 0.9)
        view.show_iteration(len(data.iterations))
    _aim_camera(server, data, extent)
    return view


def _aim_camera(server, data: SceneData, extent: float) -> None:
    """Start clients (and "reset view") behind and above the input camera, looking at the scene centre ``o``
    of the plan (a point ahead of the input camera without one)."""
    target = np.array([0.0, 0.0, extent])
    if data.iterations:
        target = np.asarray(data.scene.read(PLAN, 1, "centre"), dtype=np.float64)
    position = np.array([0.0, -0.45 * extent, -0.6 * extent])
    server.initial_camera.position = tuple(position)
    server.initial_camera.look_at = tuple(target)
    server.initial_camera.up = (0.0, -1.0, 0.0)
    for client in server.get_clients().values():
        client.camera.position = tuple(position)
        client.camera.look_at = tuple(target)


# --------------------------------------------------------------------------------------------------
# The GUI
# --------------------------------------------------------------------------------------------------
def info_markdown(data: SceneData) -> str:
    lines = [f"**{Path(data.source).name or 'scene'}** `{data.scene_id[:12]}`",
             f"backend: {data.backend or '?'}; {len(data.iterations)} iteration(s)"]
    if data.gaussians is not None:
        lines.append(f"3DGS: {data.gaussians_note}")
    lines.append("frustums: <span style='color:#2870ff'>planned</span>, "
                 "<span style='color:#ff8c00'>estimated</span>, candidates "
                 "<span style='color:#28aa46'>accepted</span> / <span style='color:#dc1e1e'>rejected by G</span> / "
                 "<span style='color:#9600c8'>chosen</span>, <span style='color:#e600a0'>video frame</span>")
    return "\n\n".join(lines)


def iteration_markdown(data: SceneData, k: int) -> str:
    if k == 0 or k > len(data.iterations):
        n = len(data.cloud(0)) if 0 in data.cloud_iterations else 0
        return f"iteration 0: the input view's cloud ({n} points)"
    it = data.iterations[k - 1]
    parts = [f"iteration {k} ({it.strategy}): {len(it.candidates)} candidate(s), "
             f"{len(it.rejected)} rejected by G"]
    if it.chosen is not None and it.scores is not None and it.chosen < len(it.scores):
        parts.append(f"chosen #{it.chosen}, score {float(it.scores[it.chosen]):.3f}")
    if k in data.cloud_iterations:
        parts.append(f"{len(data.cloud(k))} points after it")
    return "; ".join(parts)


@dataclass
class Viewer:
    """A server's viewer: the scene dropdown and the current scene's GUI and nodes."""

    server: Any
    store: Store
    choices: dict[str, str]
    view: SceneView | None = None
    gui: dict[str, Any] = field(default_factory=dict)
    _folder: Any = None
    _lock: threading.RLock = field(default_factory=threading.RLock, repr=False)

    def switch(self, scene_id: str) -> SceneView:
        """Show another scene of the store (the dropdown calls this)."""
        with self._lock:
            if self.view is not None:
                self.view.remove()
            if self._folder is not None:
                self._folder.remove()
            data = read_scene(self.store, scene_id)
            self.view = build_scene(self.server, self.store, scene_id, data)
            self._scene_gui(self.view)
            label = next((lab for lab, sid in self.choices.items() if sid == scene_id), None)
            if label is not None and self.gui["scene"].value != label:
                self.gui["scene"].value = label
            return self.view

    def _scene_gui(self, view: SceneView) -> None:
        gui, data = self.server.gui, view.data
        banner = ("navcrafter" + (" · SIMULATION" if data.label and data.label.startswith("SIMULATION") else
                                  f" · {data.label.split(':')[0][:40]}" if data.label else ""))
        gui.set_panel_label(banner)
        self._folder = folder = gui.add_folder("Scene", order=1)
        with folder:
            if data.label:
                self.gui["label"] = gui.add_markdown(f"<span style='color:#c00000'>**{data.label}**</span>")
            if data.gaussians is None:
                self.gui["no_fit"] = gui.add_markdown(f"**No 3DGS fit:** {NO_FIT}")
            self.gui["info"] = gui.add_markdown(info_markdown(data))
            for layer in LAYERS:
                if layer == "gaussians" and data.gaussians is None:
                    continue
                box = gui.add_checkbox(layer, initial_value=view.layers[layer])
                box.on_update(lambda ev, layer=layer: view.set_layer(layer, ev.target.value))
                self.gui[f"layer_{layer}"] = box
            n = len(data.iterations)
            it_slider = gui.add_slider("iteration", min=0, max=max(n, 1), step=1, initial_value=n,
                                       disabled=n == 0, hint="cloud after iteration k; cameras of 1..k")
            cum = gui.add_checkbox("cameras of earlier iterations", initial_value=view.cumulative)
            it_text = gui.add_markdown(iteration_markdown(data, n))

            def on_iteration(_ev) -> None:
                view.show_iteration(it_slider.value, cum.value)
                it_text.content = iteration_markdown(data, it_slider.value)

            it_slider.on_update(on_iteration)
            cum.on_update(on_iteration)
            self.gui.update(iteration=it_slider, cumulative=cum, iteration_info=it_text)
            refs = data.frame_refs
            if refs:
                frame_slider = gui.add_slider("video frame", min=0, max=max(len(refs) - 1, 1), step=1,
                                              initial_value=0, disabled=len(refs) < 2,
                                              hint="a synthesized frame; its camera is highlighted")
                show = gui.add_checkbox("highlight frame", initial_value=False)
                first = data.iterations[refs[0][0] - 1].frames[refs[0][1]]
                frame_img = gui.add_image(thumbnail(first), label=f"frame 0 (iteration {refs[0][0]}, #{refs[0][1]})")

                def on_frame(_ev) -> None:
                    f = int(frame_slider.value)
                    k, i = refs[f]
                    frame_img.image = thumbnail(data.iterations[k - 1].frames[i])
                    frame_img.label = f"frame {f} (iteration {k}, #{i})"
                    view.show_frame(f if show.value else None)

                frame_slider.on_update(on_frame)
                show.on_update(on_frame)
                self.gui.update(frame=frame_slider, highlight=show, frame_image=frame_img)
            if data.image is not None:
                self.gui["photo"] = gui.add_image(thumbnail(data.image), label="input photo")


def build_viewer(server, store_uri: str | Store, scene_id: str | None = None) -> Viewer:
    """The viewer of a store on a server: a dropdown of its scenes and the chosen scene (``tasks.readers
    .resolve_scene``; default the first) with its GUI. Raises ``SceneNotFound`` for an unknown scene."""
    store = store_uri if isinstance(store_uri, Store) else Store(store_uri, create=False)
    sid = resolve_scene(store, scene_id, default="first")
    choices = scene_choices(store)
    server.gui.configure_theme(show_share_button=False, control_width="medium")
    viewer = Viewer(server, store, choices)
    initial = next(lab for lab, s in choices.items() if s == sid)
    dropdown = server.gui.add_dropdown("scene", tuple(choices), initial_value=initial, order=0,
                                       hint="the store's scenes: source name (scene id)")
    viewer.gui["scene"] = dropdown
    dropdown.on_update(lambda ev: viewer.switch(choices[ev.target.value])
                       if viewer.view is None or choices[ev.target.value] != viewer.view.data.scene_id else None)
    viewer.switch(sid)
    return viewer
