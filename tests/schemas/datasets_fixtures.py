"""Writers of tiny dataset fixtures in the exact RealEstate10K, DL3DV (nerfstudio) and Tanks and Temples formats.

Each writer takes a known ``Trajectory`` (OpenCV camera-to-world poses and pixel intrinsics) and writes the
format's camera file(s) plus small rendered frames, so tests can check that the readers recover the poses
and intrinsics exactly. Every frame has a uniform background whose red channel encodes the frame index
(``frame_index_of`` decodes it, also after resizing) and a Gaussian blob in the blue channel centred on the
projection of ``Trajectory.landmark`` (``blob_centre`` measures it), to check intrinsics after resizing.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from navcrafter.models.camera.cameras import look_at, project

GL_CV_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class Trajectory:
    c2w: np.ndarray        # [N, 4, 4] OpenCV camera-to-world
    K: np.ndarray          # [N, 3, 3] pixels of width x height
    width: int
    height: int
    landmark: np.ndarray   # [3] a world point seen by every camera

    def __len__(self) -> int:
        return len(self.c2w)


def circle_trajectory(n: int = 20, width: int = 64, height: int = 48, fx: float = 55.0, fy: float = 50.0,
                      cx: float = 30.5, cy: float = 25.0, radius: float = 2.0, arc_rad: float = 1.2,
                      varying_focal: bool = False) -> Trajectory:
    """A camera moving on an arc around the point (0, 0.3, 5), always looking at it, its height wobbling.

    Intrinsics are deliberately non-square and off-centre (fx != fy, cx != W/2, cy != H/2) so that swapped
    axes show. ``varying_focal`` gives every frame its own focal length.
    """
    centre = np.array([0.0, 0.3, 5.0])
    out = []
    for i, th in enumerate(np.linspace(-arc_rad / 2, arc_rad / 2, n)):
        eye = centre + np.array([radius * np.sin(th), 0.4 * np.sin(3 * th) - 0.2, -radius * np.cos(th)])
        out.append(look_at(eye, centre + np.array([0.05 * i / n, 0.0, 0.0])))
    K = np.tile(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), (n, 1, 1))
    if varying_focal:
        K[:, 0, 0] *= 1 + 0.02 * np.arange(n)
        K[:, 1, 1] *= 1 + 0.02 * np.arange(n)
    return Trajectory(np.stack(out), K, width, height, centre + np.array([0.25, -0.15, 0.1]))


# --------------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------------
def index_red(index: int) -> int:
    if not 0 <= index < 25:
        raise ValueError("fixture frames encode indices 0..24")
    return 5 + 10 * index


def frame_index_of(image: np.ndarray) -> int:
    """The index encoded in a fixture frame (robust to resizing and JPEG)."""
    return int(round((float(np.median(image[..., 0])) - 5) / 10))


def render_frame(index: int, c2w: np.ndarray, K: np.ndarray, width: int, height: int, landmark: np.ndarray,
                 sigma: float = 1.5) -> np.ndarray:
    img = np.zeros((height, width, 3), dtype=np.uint8)
    img[..., 0] = index_red(index)
    img[..., 1] = 100
    (u, v), = project(landmark[None], c2w, K)[0]
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    blob = np.exp(-((jj - u) ** 2 + (ii - v) ** 2) / (2 * sigma**2))
    img[..., 2] = np.round(255 * blob).astype(np.uint8)
    return img


def blob_centre(image: np.ndarray) -> np.ndarray:
    """Intensity-weighted centre ``(u, v)`` of the blue blob, in pixel coordinates (pixel centres at +0.5)."""
    w = image[..., 2].astype(np.float64)
    w = np.where(w > 8, w, 0.0)
    ii, jj = np.mgrid[: image.shape[0], : image.shape[1]]
    return np.array([(w * (jj + 0.5)).sum() / w.sum(), (w * (ii + 0.5)).sum() / w.sum()])


def landmark_pixel(c2w: np.ndarray, K: np.ndarray, landmark: np.ndarray) -> np.ndarray:
    return project(np.asarray(landmark)[None], c2w, K)[0][0]


def _save(img: np.ndarray, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() in (".jpg", ".jpeg"):
        Image.fromarray(img).save(path, quality=95)
    else:
        Image.fromarray(img).save(path)


def _row(values) -> str:
    return " ".join(repr(float(v)) for v in values)


# --------------------------------------------------------------------------------------------------
# RealEstate10K
# --------------------------------------------------------------------------------------------------
def re10k_timestamps(n: int) -> list[int]:
    return [1_001_000 + 33_367 * i for i in range(n)]


def write_re10k(root: Path, traj: Trajectory, sequence: str = "0a1b2c3d4e5f6a7b", split: str | None = "test",
                ext: str = ".png", frames: bool = True) -> Path:
    """``<root>/<split>/<sequence>.txt`` (URL line, then ``ts fx fy cx cy 0 0 w2c[3x4]`` with intrinsics
    normalised by the image size) and ``<root>/<split>/<sequence>/<ts>.png``."""
    base = Path(root) if split is None else Path(root) / split
    base.mkdir(parents=True, exist_ok=True)
    lines = [f"https://www.youtube.com/watch?v={sequence[:11]}"]
    for i, ts in enumerate(re10k_timestamps(len(traj))):
        K, w2c = traj.K[i], np.linalg.inv(traj.c2w[i])
        intr = [K[0, 0] / traj.width, K[1, 1] / traj.height, K[0, 2] / traj.width, K[1, 2] / traj.height]
        lines.append(f"{ts} {_row(intr)} 0.0 0.0 {_row(w2c[:3].reshape(-1))}")
        if frames:
            img = render_frame(i, traj.c2w[i], traj.K[i], traj.width, traj.height, traj.landmark)
            _save(img, base / sequence / f"{ts}{ext}")
    txt = base / f"{sequence}.txt"
    txt.write_text("\n".join(lines) + "\n")
    return txt


# --------------------------------------------------------------------------------------------------
# DL3DV (nerfstudio transforms.json)
# --------------------------------------------------------------------------------------------------
def write_dl3dv(root: Path, traj: Trajectory, scene: str = "scene_a", downscale: int = 1,
                images_dir: str | None = None, per_frame_intrinsics: bool = False, shuffle: bool = True,
                nerfstudio_subfolder: bool = False) -> Path:
    """``<root>/<scene>/transforms.json`` with OpenGL camera-to-world ``transform_matrix`` and
    ``file_path = images/frame_00001.png``.

    ``downscale > 1`` imitates DL3DV's downscaled releases: the json keeps the full-resolution intrinsics
    and size (``downscale`` times the trajectory's) while the frames (at the trajectory's size) are
    written to ``images_<downscale>/`` (or ``images_dir``). ``shuffle`` lists frames out of order.
    """
    folder = Path(root) / scene
    if nerfstudio_subfolder:
        folder = folder / "nerfstudio"
    folder.mkdir(parents=True, exist_ok=True)
    s = float(downscale)
    img_folder = images_dir or ("images" if downscale == 1 else f"images_{downscale}")
    intr = lambda K: {"fl_x": K[0, 0] * s, "fl_y": K[1, 1] * s, "cx": K[0, 2] * s, "cy": K[1, 2] * s}
    meta: dict = {"w": traj.width * downscale, "h": traj.height * downscale, "camera_model": "OPENCV",
                  "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}
    if not per_frame_intrinsics:
        meta.update(intr(traj.K[0]))
    frames = []
    for i in range(len(traj)):
        name = f"frame_{i + 1:05d}.png"
        fr = {"file_path": f"images/{name}", "transform_matrix": (traj.c2w[i] @ GL_CV_FLIP).tolist(),
              "colmap_im_id": i + 1}
        if per_frame_intrinsics:
            fr.update(intr(traj.K[i]))
        frames.append(fr)
        img = render_frame(i, traj.c2w[i], traj.K[i], traj.width, traj.height, traj.landmark)
        _save(img, folder / img_folder / name)
    if shuffle:
        order = np.random.default_rng(7).permutation(len(frames))
        frames = [frames[k] for k in order]
    meta["frames"] = frames
    meta["applied_transform"] = np.eye(4)[:3].tolist()
    js = folder / "transforms.json"
    js.write_text(json.dumps(meta, indent=1))
    return js


# --------------------------------------------------------------------------------------------------
# Tanks and Temples (.log + images [+ COLMAP cameras.txt])
# --------------------------------------------------------------------------------------------------
def write_tnt(root: Path, traj: Trajectory, scene: str = "Barn", cameras_txt: str | None = "sparse/0/cameras.txt",
              camera_model: str = "PINHOLE", cameras_scale: int = 1, ext: str = ".jpg") -> Path:
    """``<root>/<scene>/<scene>_COLMAP_SfM.log`` (blocks ``i i 0`` + 4x4 camera-to-world), images
    ``<root>/<scene>/images/000001.jpg`` and, unless ``cameras_txt`` is None, a COLMAP ``cameras.txt`` there
    (for images ``cameras_scale`` times larger than the ones written). Returns the log's path."""
    folder = Path(root) / scene
    (folder / "images").mkdir(parents=True, exist_ok=True)
    blocks = []
    for i in range(len(traj)):
        blocks.append(f"{i} {i} 0")
        blocks.extend(_row(r) for r in traj.c2w[i])
        img = render_frame(i, traj.c2w[i], traj.K[i], traj.width, traj.height, traj.landmark)
        _save(img, folder / "images" / f"{i + 1:06d}{ext}")
    log = folder / f"{scene}_COLMAP_SfM.log"
    log.write_text("\n".join(blocks) + "\n")
    if cameras_txt is not None:
        K, s = traj.K[0], cameras_scale
        w, h = traj.width * s, traj.height * s
        if camera_model == "PINHOLE":
            params = [K[0, 0] * s, K[1, 1] * s, K[0, 2] * s, K[1, 2] * s]
        elif camera_model == "SIMPLE_RADIAL":
            params = [K[0, 0] * s, K[0, 2] * s, K[1, 2] * s, 0.0]
        elif camera_model == "OPENCV":
            params = [K[0, 0] * s, K[1, 1] * s, K[0, 2] * s, K[1, 2] * s, 0.0, 0.0, 0.0, 0.0]
        else:
            raise ValueError(camera_model)
        p = folder / cameras_txt
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("# Camera list with one line of data per camera:\n"
                     "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n"
                     f"1 {camera_model} {w} {h} {_row(params)}\n")
    return log
