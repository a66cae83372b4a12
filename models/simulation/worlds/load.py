"""Reading scans into worlds: meshes, point clouds and posed RGB-D sequences, in metres with z up.

Formats (chosen by the path):

* **meshes** (``.obj`` + ``.mtl`` + images, ``.ply`` with faces, ``.glb`` / ``.gltf``, ``.off``, ``.stl``), read
  with trimesh: a texture (``map_Kd``, a glTF base-colour texture, a PLY's ``TextureFile`` with per-vertex
  texture coordinates) gives ``texture`` colour; vertex or face colours give ``vertex`` colour; none gives the
  labelled ``neutral`` shading (never invented texture). A texture that an MTL names but that is missing is
  reported as a warning and that part falls back to vertex colour, or neutral grey.
* **point clouds** (``.pcd``, ``.xyz``, ``.xyzrgb``, ``.pts``, ``.ply`` without faces), read with Open3D and
  turned into a surface by ball pivoting (``create_from_point_cloud_ball_pivoting`` at 1.5, 3 and 6 times the
  median point spacing). Ball pivoting only joins measured points: where the scan has holes the surface has
  holes too, and those render as *no data*. Poisson reconstruction would close them with extrapolated
  membranes that the scan never saw (its density trimming removes only part of them), which is the invented
  geometry the ground truth must not contain. Normals: the file's, else estimated and oriented towards the
  scan's centre (rooms are scanned from inside); each triangle then faces the side of its points' normals.
* **posed RGB-D sequences** (a folder; ``RGBD_LAYOUT``), fused by TSDF (Open3D's ``UniformTSDFVolume``) into a
  vertex-coloured mesh.

Then: ``scale`` (file units to metres), the up axis (given, or the normal of the floor found by RANSAC
plane fits, ``find_up``), the floor moved to z = 0 and the scan centred in x, y. Bad scans raise ``WorldError``
naming the file and the fix: missing, empty or unreadable files, no surface, non-finite vertices, a size far
from a room's in metres (suggesting ``--scale``), no floor found (suggesting ``--up``).
"""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np
import open3d as o3d

from navcrafter.models.simulation.worlds import WorldError
from navcrafter.models.simulation.worlds.world import NEUTRAL_NOTE, World, ransac_planes

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".off", ".stl")
CLOUD_SUFFIXES = (".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts", ".ply")
MIN_SIZE_M, MAX_SIZE_M = 1.0, 2000.0  # diagonal of the scan's bounds, metres
UP_AXES = {"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1), "-x": (-1, 0, 0), "-y": (0, -1, 0), "-z": (0, 0, -1)}
MAX_CLOUD_POINTS = 300_000
TSDF_RESOLUTION = 256

RGBD_LAYOUT = """A posed RGB-D sequence is a folder holding:
  color/ (or rgb/, image/)  NNNN.png|.jpg   8-bit colour frames
  depth/                    NNNN.png        16-bit depth frames (0 = no measurement), same count, paired by
                                            sorted file name with the colour frames
  camera.json               {"fx", "fy", "cx", "cy", "width", "height"} of the depth/colour camera (pixels),
                            optional "depth_scale" (depth units per metre, default 1000; TUM uses 5000) and
                            "depth_max" (metres, default 4.0); or intrinsic.json in Open3D's
                            PinholeCameraIntrinsic format (width, height, intrinsic_matrix column-major)
  trajectory.log            Redwood / Open3D trajectory: per frame a line 'i i+1 n' then the 4 rows of the
                            camera-to-world matrix (metres)
    or poses.txt            TUM: per frame, in frame order, 'timestamp tx ty tz qx qy qz qw' (camera-to-world)
Colour and depth are registered (same camera)."""


def _fail(path: Path, what: str) -> WorldError:
    return WorldError(f"{path}: {what}")


# --------------------------------------------------------------------------------------------------
# Meshes
# --------------------------------------------------------------------------------------------------
def missing_textures(obj: Path) -> list[str]:
    """Warnings for the material libraries and textures an OBJ names but that are missing."""
    out = []
    try:
        text = obj.read_text(errors="replace")
    except OSError:
        return out
    for lib in re.findall(r"^\s*mtllib\s+(.+?)\s*$", text, flags=re.M):
        mtl = obj.parent / lib
        if not mtl.is_file():
            out.append(f"{obj}: the material library {lib} it names is missing: no textures or material colours "
                       f"(vertex colour or neutral shading instead); put {lib} beside the OBJ")
            continue
        for tex in re.findall(r"^\s*map_Kd\s+(?:-\S+\s+\S+\s+)*(.+?)\s*$", mtl.read_text(errors="replace"),
                              flags=re.M):
            if not (mtl.parent / tex).is_file():
                out.append(f"{mtl}: the texture {tex} it names is missing: the faces using it fall back to vertex "
                           f"colour, or neutral grey shading; put {tex} beside the MTL")
    return out


def _geometries(loaded) -> list:
    import trimesh

    if isinstance(loaded, trimesh.Scene):
        return [g for g in loaded.dump(concatenate=False) if isinstance(g, trimesh.Trimesh)]
    return [loaded] if isinstance(loaded, trimesh.Trimesh) else []


def _image_of(material) -> np.ndarray | None:
    img = getattr(material, "image", None)
    if img is None:
        img = getattr(material, "baseColorTexture", None)
    if img is None:
        return None
    return np.asarray(img.convert("RGB"), dtype=np.uint8)


def read_mesh(path: Path) -> tuple[dict, list[str]]:
    """Triangle soup and colour of a mesh file (its own units and axes), and warnings."""
    import trimesh

    notes = missing_textures(path) if path.suffix.lower() == ".obj" else []
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loaded = trimesh.load(str(path), process=False)
    except Exception as exc:
        raise _fail(path, f"cannot be read as a {path.suffix} mesh ({type(exc).__name__}: {exc}); re-export it "
                    f"(OBJ+MTL, PLY or GLB) or check that the file is complete") from exc
    geoms = [g for g in _geometries(loaded) if len(g.faces)]
    if not geoms:
        raise _fail(path, "contains no triangles; export the scan as a mesh with faces (or as a point cloud)")
    corners, rgb, uvs, tid, textures = [], [], [], [], []
    kinds = set()
    for g in geoms:
        faces = np.asarray(g.faces, dtype=np.int64)
        V = np.asarray(g.vertices, dtype=np.float64)
        corners.append(V[faces])
        vis = g.visual
        F = len(faces)
        c_rgb = np.full((F, 3, 3), np.nan)
        t_id = np.full(F, -1, dtype=np.int32)
        uv = np.zeros((F, 3, 2), dtype=np.float32)
        if vis.kind == "texture" and getattr(vis, "uv", None) is not None and len(vis.uv) == len(V):
            img = _image_of(vis.material)
            if img is not None:
                textures.append(img)
                t_id[:] = len(textures) - 1
                uv = np.asarray(vis.uv, dtype=np.float32)[faces]
                kinds.add("texture")
        elif vis.kind == "vertex":
            c_rgb = np.asarray(vis.vertex_colors, dtype=np.float64)[faces][..., :3] / 255.0
            kinds.add("vertex")
        elif vis.kind == "face":
            c_rgb = np.repeat(np.asarray(vis.face_colors, dtype=np.float64)[:, None, :3] / 255.0, 3, axis=1)
            kinds.add("vertex")
        rgb.append(c_rgb)
        uvs.append(uv)
        tid.append(t_id)
    out = {"corners": np.concatenate(corners)}
    rgb_all = np.concatenate(rgb)
    if "texture" in kinds:
        out.update(colour="texture", uvs=np.concatenate(uvs), texture_id=np.concatenate(tid).astype(np.int32),
                   textures=textures)
        if np.isfinite(rgb_all).any():
            out["corner_rgb"] = np.where(np.isfinite(rgb_all), rgb_all, 0.7).astype(np.float32)
        if (out["texture_id"] < 0).any():
            notes.append(f"{path}: {(out['texture_id'] < 0).mean():.0%} of the faces have no texture: drawn in "
                         f"their vertex colour, or flat neutral grey")
    elif kinds:
        out.update(colour="vertex", corner_rgb=np.where(np.isfinite(rgb_all), rgb_all, 0.7).astype(np.float32))
    else:
        out["colour"] = "neutral"
    return out, notes


# --------------------------------------------------------------------------------------------------
# Point clouds
# --------------------------------------------------------------------------------------------------
def _ply_has_faces(path: Path) -> bool:
    with open(path, "rb") as f:
        head = f.read(4096).split(b"end_header")[0].decode("ascii", errors="replace")
    m = re.search(r"element\s+face\s+(\d+)", head)
    return bool(m and int(m.group(1)) > 0)


def read_cloud(path: Path) -> o3d.geometry.PointCloud:
    try:
        pcd = o3d.io.read_point_cloud(str(path))
    except Exception as exc:  # Open3D mostly warns and returns an empty cloud instead
        raise _fail(path, f"cannot be read as a point cloud ({exc}); re-export it as PLY or PCD") from exc
    if len(pcd.points) == 0:
        raise _fail(path, "contains no points (or is not a readable point cloud); re-export it as PLY or PCD")
    return pcd


def cloud_surface(pcd: o3d.geometry.PointCloud, path: Path) -> tuple[dict, list[str]]:
    """Ball-pivoting surface of a point cloud (see the module docstring), vertex-coloured where it has colours."""
    notes = []
    pts = np.asarray(pcd.points)
    if not np.isfinite(pts).all():
        raise _fail(path, f"{int((~np.isfinite(pts).all(1)).sum())} points are NaN or infinite; remove them "
                    f"(Open3D: remove_non_finite_points) and try again")
    if len(pts) > MAX_CLOUD_POINTS:
        ext = np.linalg.norm(pts.max(0) - pts.min(0))
        voxel = ext / 400.0
        while True:
            down = pcd.voxel_down_sample(voxel)
            if len(down.points) <= MAX_CLOUD_POINTS:
                break
            voxel *= 1.3
        notes.append(f"{path}: {len(pts)} points thinned to {len(down.points)} (voxel {voxel:.3g}) before meshing")
        pcd = down
    spacing = float(np.median(np.asarray(pcd.compute_nearest_neighbor_distance())))
    had_normals = pcd.has_normals()
    if not had_normals:
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * spacing, max_nn=30))
        centre = np.asarray(pcd.get_axis_aligned_bounding_box().get_center())
        pcd.orient_normals_towards_camera_location(centre)
        notes.append(f"{path}: no normals in the file: estimated, and oriented towards the scan's centre "
                     f"(occupancy by ray parity, not by the surface's facing)")
    radii = o3d.utility.DoubleVector([1.5 * spacing, 3 * spacing, 6 * spacing])
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(pcd, radii)
    if len(mesh.triangles) == 0:
        raise _fail(path, "ball pivoting made no surface from the points (too sparse or too noisy); give a denser "
                    "point cloud or a mesh")
    V, T = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    corners = V[T]
    # each triangle faces the side of its points' normals
    N = np.asarray(pcd.normals)
    vn = N[_nearest(np.asarray(pcd.points), V)][T].sum(1)
    fn = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    flip = (fn * vn).sum(1) < 0
    corners[flip] = corners[flip][:, ::-1]
    out = {"corners": corners, "colour": "neutral", "occupancy": "backface" if had_normals else "parity"}
    if pcd.has_colors():
        C = np.asarray(pcd.colors)[_nearest(np.asarray(pcd.points), V)][T]
        C[flip] = C[flip][:, ::-1]
        out.update(colour="vertex", corner_rgb=C.astype(np.float32))
    return out, notes


def _nearest(points: np.ndarray, queries: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    return cKDTree(points).query(queries, k=1)[1]


# --------------------------------------------------------------------------------------------------
# Posed RGB-D sequences
# --------------------------------------------------------------------------------------------------
def _frames(folder: Path, names: tuple[str, ...]) -> list[Path]:
    for n in names:
        d = folder / n
        if d.is_dir():
            return sorted(p for p in d.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    return []


def _tum_pose(row: list[float]) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    M = np.eye(4)
    M[:3, :3] = Rotation.from_quat(row[4:8]).as_matrix()
    M[:3, 3] = row[1:4]
    return M


def read_poses(folder: Path) -> np.ndarray:
    log, tum = folder / "trajectory.log", folder / "poses.txt"
    if log.is_file():
        rows = [r.split() for r in log.read_text().splitlines() if r.strip()]
        if len(rows) % 5:
            raise _fail(log, "a Redwood trajectory has 5 lines per frame (a header and 4 matrix rows); fix the file")
        try:
            M = np.asarray([[float(x) for x in r] for i, r in enumerate(rows) if i % 5], dtype=np.float64)
        except ValueError as exc:
            raise _fail(log, f"not numeric ({exc}); fix the file") from None
        return M.reshape(-1, 4, 4)
    if tum.is_file():
        rows = [r.split() for r in tum.read_text().splitlines() if r.strip() and not r.startswith("#")]
        if any(len(r) != 8 for r in rows):
            raise _fail(tum, "each TUM pose line needs 8 numbers 'timestamp tx ty tz qx qy qz qw'; fix the file")
        return np.stack([_tum_pose([float(x) for x in r]) for r in rows])
    raise _fail(folder, f"no camera poses (trajectory.log or poses.txt).\n{RGBD_LAYOUT}")


def read_camera(folder: Path) -> tuple[o3d.camera.PinholeCameraIntrinsic, float, float]:
    cam, o3d_json = folder / "camera.json", folder / "intrinsic.json"
    if cam.is_file():
        try:
            c = json.loads(cam.read_text())
            intr = o3d.camera.PinholeCameraIntrinsic(int(c["width"]), int(c["height"]), float(c["fx"]),
                                                     float(c["fy"]), float(c["cx"]), float(c["cy"]))
        except (KeyError, ValueError, TypeError, json.JSONDecodeError) as exc:
            raise _fail(cam, f"needs numbers fx, fy, cx, cy, width, height ({exc}); fix the file") from None
        return intr, float(c.get("depth_scale", 1000.0)), float(c.get("depth_max", 4.0))
    if o3d_json.is_file():
        return o3d.io.read_pinhole_camera_intrinsic(str(o3d_json)), 1000.0, 4.0
    raise _fail(folder, f"no camera intrinsics (camera.json or intrinsic.json).\n{RGBD_LAYOUT}")


def fuse_rgbd(folder: Path, voxel: float = 0.01) -> tuple[dict, list[str]]:
    """TSDF fusion (Open3D ``UniformTSDFVolume``) of a posed RGB-D sequence into a vertex-coloured mesh."""
    colour, depth = _frames(folder, ("color", "rgb", "image")), _frames(folder, ("depth",))
    if not colour or not depth:
        raise _fail(folder, f"not a mesh, point cloud or RGB-D sequence (no color/ and depth/ frames).\n{RGBD_LAYOUT}")
    if len(colour) != len(depth):
        raise _fail(folder, f"{len(colour)} colour frames but {len(depth)} depth frames; give one depth per colour")
    poses = read_poses(folder)
    if len(poses) != len(colour):
        raise _fail(folder, f"{len(poses)} camera poses for {len(colour)} frames; give one pose per frame")
    intr, depth_scale, depth_max = read_camera(folder)
    if not np.isfinite(poses).all():
        raise _fail(folder, "a camera pose is not finite; fix the pose file")
    frames, lo, hi = [], np.full(3, np.inf), np.full(3, -np.inf)
    for c, d, c2w in zip(colour, depth, poses, strict=True):
        ci, di = o3d.io.read_image(str(c)), o3d.io.read_image(str(d))
        if np.asarray(ci).size == 0 or np.asarray(di).size == 0:
            raise _fail(c if np.asarray(ci).size == 0 else d, "cannot be read as an image; replace it")
        if np.asarray(ci).ndim == 3 and np.asarray(ci).shape[2] == 4:
            ci = o3d.geometry.Image(np.ascontiguousarray(np.asarray(ci)[..., :3]))
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            ci, di, depth_scale=depth_scale, depth_trunc=depth_max, convert_rgb_to_intensity=False)
        pts = np.asarray(o3d.geometry.PointCloud.create_from_rgbd_image(rgbd, intr, np.linalg.inv(c2w)).points)
        if len(pts):
            lo, hi = np.minimum(lo, pts.min(0)), np.maximum(hi, pts.max(0))
        frames.append((rgbd, c2w))
    if not np.isfinite(lo).all():
        raise _fail(folder, "no valid depth in any frame (all zero or beyond depth_max); check depth_scale in "
                    "camera.json")
    # Open3D 0.20's ScalableTSDFVolume returned empty meshes here (checked on this sequence), the uniform volume
    # over the frames' bounds does not; at most TSDF_RESOLUTION voxels a side (coarser voxels for big scenes)
    length = float((hi - lo).max()) + 8 * voxel
    res = int(min(TSDF_RESOLUTION, np.ceil(length / voxel)))
    vol = o3d.pipelines.integration.UniformTSDFVolume(
        length=length, resolution=res, sdf_trunc=4 * length / res,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8,
        origin=(lo - 4 * voxel).reshape(3, 1).astype(np.float64))
    for rgbd, c2w in frames:
        vol.integrate(rgbd, intr, np.linalg.inv(c2w))
    voxel = length / res
    mesh = vol.extract_triangle_mesh()
    if len(mesh.triangles) == 0:
        raise _fail(folder, "TSDF fusion made no surface (depth all zero or beyond depth_max, or poses wrong); "
                    "check depth_scale in camera.json")
    V, T = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    C = np.asarray(mesh.vertex_colors)[T].astype(np.float32)
    corners = V[T]
    # triangles face the cameras that saw them
    centres = poses[:, :3, 3]
    fc = corners.mean(1)
    fn = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    to_cam = centres[_nearest(centres, fc)] - fc
    flip = (fn * to_cam).sum(1) < 0
    corners[flip], C[flip] = corners[flip][:, ::-1], C[flip][:, ::-1]
    cam_up = -poses[:, :3, 1].mean(0)  # OpenCV cameras: y points down in the image
    return {"corners": corners, "colour": "vertex", "corner_rgb": C, "up_hint": cam_up / np.linalg.norm(cam_up)}, [
        f"{folder}: {len(colour)} RGB-D frames fused (TSDF voxel {voxel:.3g} m)"]


# --------------------------------------------------------------------------------------------------
# Up axis, scale, frame
# --------------------------------------------------------------------------------------------------
def rotation_to_z(up: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the unit vector ``up`` to +z."""
    u = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    z = np.array([0.0, 0.0, 1.0])
    c = float(u @ z)
    if c < -1 + 1e-9:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(u, z)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def find_up(corners: np.ndarray, seed: int = 0, hint: np.ndarray | None = None) -> tuple[np.ndarray, float] | None:
    """The floor's up normal and the floor's height along it, by RANSAC planes (Open3D ``segment_plane``), or
    None. A floor candidate bounds the scan (>= 95 % of its surface on one side), among those the one across
    which the scan is thinnest (rooms are wider than tall); between it and an opposite bounding plane (the
    ceiling) the floor is the one nearer most of the remaining surface (furniture stands on the floor).
    ``hint`` (an RGB-D sequence's mean camera up, people hold cameras upright): the bounding plane within 25
    degrees of it, else the hint itself."""
    pts, thr, fits, rest = ransac_planes(corners, 30000, 6, 0.05, seed)
    diag = float(np.linalg.norm(pts.max(0) - pts.min(0)))
    planes = []
    for n, d, count in fits:
        s = pts @ n + d
        if (s < thr).mean() > (s > -thr).mean():
            n, d, s = -n, -d, -s
        planes.append({"n": n, "d": d, "bounding": (s > -thr).mean() >= 0.95, "extent": float(np.percentile(s, 98)),
                       "count": count})
    if hint is not None:  # the cameras' up (RGB-D): the floor is a bounding plane within 25 degrees of it
        near = [p for p in planes if p["bounding"] and p["n"] @ hint > np.cos(np.deg2rad(25))]
        if near:
            best = max(near, key=lambda p: p["count"])
            return best["n"], -best["d"]
        return hint, float(np.percentile(pts @ hint, 0.5))
    bounding = [p for p in planes if p["bounding"]]
    if not bounding:
        return None
    best = min(bounding, key=lambda p: (round(p["extent"] / (0.1 * diag)), -p["count"]))
    opposite = [p for p in bounding if p["n"] @ best["n"] < -0.95]
    if opposite and rest.sum() >= 0.02 * len(pts):
        h = pts[rest] @ best["n"] + best["d"]
        if np.median(h) > best["extent"] / 2:
            best = max(opposite, key=lambda p: p["count"])
    return best["n"], -best["d"]


def frame_transform(corners: np.ndarray, up: str, seed: int = 0,
                    hint: np.ndarray | None = None) -> tuple[np.ndarray, bool, str]:
    """The 4x4 rigid map from the (scaled) scan's frame to the ground-truth frame (up = +z, floor at z = 0,
    centred in x, y), whether a floor was found or given, and how the up axis was chosen."""
    if up == "auto":
        found = find_up(corners, seed, hint)
        if found is None:
            raise WorldError("no floor plane found (RANSAC); give the up axis with --up x|y|z|-x|-y|-z")
        n, h = found
        how = f"floor plane by RANSAC: up = {np.round(n, 3).tolist()} in the file's axes"
    elif up in UP_AXES:
        n, h, how = np.asarray(UP_AXES[up], dtype=np.float64), None, f"given: {up}"
    else:
        raise WorldError(f"unknown up axis {up!r}; choose auto, {', '.join(UP_AXES)}")
    R = rotation_to_z(n)
    p = corners.reshape(-1, 3) @ R.T
    floor_z = float(h) if h is not None else float(np.percentile(p[:, 2], 0.5))
    lo, hi = p.min(0), p.max(0)
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = [-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -floor_z]
    return M, True, how


def load_world(path: str | Path, *, scale: float = 1.0, up: str = "auto", name: str | None = None,
               seed: int = 0) -> World:
    """Read a scan (see the module docstring) into a ``World`` in the ground-truth frame."""
    path = Path(path).expanduser()
    if not path.exists():
        raise _fail(path, "does not exist; check the path")
    if not (scale > 0 and np.isfinite(scale)):
        raise _fail(path, f"--scale must be a positive number, got {scale}")
    suffix = path.suffix.lower()
    hint = None
    if path.is_dir():
        data, notes, fmt = *fuse_rgbd(path), "rgbd"
        hint = data.pop("up_hint")
    else:
        if path.stat().st_size == 0:
            raise _fail(path, "the file is empty (0 bytes); export the scan again")
        if suffix == ".ply" and not _ply_has_faces(path) or suffix in CLOUD_SUFFIXES and suffix != ".ply":
            data, notes = cloud_surface(read_cloud(path), path)
            fmt = "point cloud"
        elif suffix in MESH_SUFFIXES:
            data, notes = read_mesh(path)
            fmt = "mesh"
        else:
            raise _fail(path, f"unknown scan format {suffix!r}; give a mesh ({', '.join(MESH_SUFFIXES)}), a point "
                        f"cloud ({', '.join(CLOUD_SUFFIXES)}) or a folder with a posed RGB-D sequence")
    corners = np.asarray(data.pop("corners"), dtype=np.float64)
    bad = ~np.isfinite(corners).all(axis=(1, 2))
    if bad.any():
        raise _fail(path, f"{int(bad.sum())} of {len(corners)} triangles have NaN or infinite vertices; clean the "
                    f"scan (e.g. Open3D remove_non_finite / MeshLab) and try again")
    corners = corners * scale
    size = float(np.linalg.norm(corners.reshape(-1, 3).max(0) - corners.reshape(-1, 3).min(0)))
    if size < MIN_SIZE_M:
        raise _fail(path, f"the scan is {size:.3g} m across at --scale {scale:g}: far too small for a scene in "
                    f"metres; if its unit is not the metre, give --scale (e.g. --scale 1000 for a scan in km, or "
                    f"the factor to metres); a single object needs the room around it to be explored")
    if size > MAX_SIZE_M:
        raise _fail(path, f"the scan is {size:.3g} m across at --scale {scale:g}: far too large for a scene in "
                    f"metres; if it is in millimetres give --scale 0.001, in centimetres --scale 0.01")
    try:
        M, floor, how = frame_transform(corners, up, seed, hint)
    except WorldError as exc:
        raise _fail(path, str(exc)) from None
    corners = corners @ M[:3, :3].T + M[:3, 3]
    if data["colour"] == "neutral":
        notes.append(f"{path}: {NEUTRAL_NOTE}")
    for n in notes:
        warnings.warn(n, stacklevel=2)
    to_gt = M.copy()
    to_gt[:3, :3] *= scale  # file coordinates -> ground truth (metres)
    info = {"file": str(path), "format": fmt, "scale": scale, "up": how, "file_to_world": to_gt.tolist(),
            "colour": data["colour"], "triangles": len(corners), "warnings": notes,
            "occupancy": data.pop("occupancy", "backface")}
    if data["colour"] == "neutral":
        info["colour_note"] = NEUTRAL_NOTE
    return World(name or path.stem, corners, data.pop("colour"), data.get("corner_rgb"), data.get("uvs"),
                 data.get("texture_id"), data.get("textures", []), floor, info)
