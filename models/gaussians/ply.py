"""The standard 3D Gaussian Splatting PLY (as the original 3DGS code writes it; read by common splat viewers).

One ``vertex`` element, binary little-endian, all properties ``float`` (float32), in this order::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_{3(K-1)-1}  opacity  scale_0..2  rot_0..3

``f_dc_*`` are the DC SH coefficients (R, G, B); ``f_rest_*`` the higher bands in 3DGS's channel-major
order (all of red's ``K-1`` coefficients, then green's, then blue's); ``opacity`` is the logit, ``scale_*``
the log-scales, ``rot_*`` the quaternion (w, x, y, z); normals are written as zeros. Header ``comment``
lines may carry a label (navcrafter writes the simulation-mode label there). Float32 models round-trip
bit for bit through ``save_ply`` / ``load_ply``; ``load_gaussian_ply`` is the checked load for rendering a PLY
from any tool (no NaN/inf, no zero quaternions, at least one Gaussian; quaternions normalised).
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from navcrafter.models.gaussians.model import GaussianModel
from navcrafter.models.gaussians.sh import num_sh_bases

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_MAX_HEADER_LINE = 4096  # bytes: a longer header line means the file is no PLY (binary data)


def property_names(sh_degree: int) -> list[str]:
    """The vertex properties of a 3DGS PLY of SH degree ``sh_degree``, in file order."""
    n_rest = 3 * (num_sh_bases(sh_degree) - 1)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(n_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def _comment_lines(comments: str | list[str] | tuple[str, ...]) -> list[str]:
    items = [comments] if isinstance(comments, str) else list(comments)
    lines = []
    for item in items:
        for line in str(item).splitlines():
            line = line.encode("ascii", errors="replace").decode("ascii").strip()
            lines.append(f"comment {line}" if line else "comment")
    return lines


def to_structured(model: GaussianModel) -> np.ndarray:
    """The model as a numpy structured array with the 3DGS PLY vertex layout (little-endian float32)."""
    names = property_names(model.sh_degree)
    arr = np.zeros(len(model), dtype=np.dtype([(name, "<f4") for name in names]))

    def put(prefix: list[str], values: torch.Tensor) -> None:
        v = values.detach().cpu().numpy().astype("<f4", copy=False).reshape(len(model), -1)
        for i, name in enumerate(prefix):
            arr[name] = v[:, i]

    put(["x", "y", "z"], model.means)
    put(["f_dc_0", "f_dc_1", "f_dc_2"], model.sh_dc)
    rest = model.sh_rest.transpose(1, 2).reshape(len(model), -1)  # [N, 3 * (K-1)], channel-major
    put([f"f_rest_{i}" for i in range(rest.shape[1])], rest)
    put(["opacity"], model.opacity_logits)
    put(["scale_0", "scale_1", "scale_2"], model.log_scales)
    put(["rot_0", "rot_1", "rot_2", "rot_3"], model.quats)
    return arr


def save_ply(path: str | Path, model: GaussianModel, *, comments: str | list[str] | tuple[str, ...] = ()) -> Path:
    """Write ``model`` as a 3DGS PLY (atomically: a temporary file renamed into place). ``comments`` become
    header comment lines (non-ASCII characters are replaced by ``?``)."""
    path = Path(path)
    arr = to_structured(model)
    header = ["ply", "format binary_little_endian 1.0", *_comment_lines(comments), f"element vertex {len(arr)}"]
    header += [f"property float {name}" for name in arr.dtype.names]
    header.append("end_header")
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(arr.tobytes())
    os.replace(tmp, path)
    return path


@dataclass(frozen=True)
class PlyHeader:
    format: str
    comments: tuple[str, ...]
    vertex_count: int
    vertex_dtype: np.dtype
    data_offset: int  # bytes from the start of the file to the vertex data


def read_ply_header(path: str | Path) -> PlyHeader:
    """Parse the header of a binary little-endian PLY whose first element is ``vertex`` (scalar properties)."""
    with open(path, "rb") as fh:
        if fh.readline(64).strip() != b"ply":
            raise ValueError(f"{path}: not a PLY file (it does not start with the line 'ply'); give a 3D Gaussian "
                             "Splatting .ply as written by navcrafter, the INRIA 3DGS code or gsplat")
        fmt, comments, count, props, element = "", [], None, [], None
        for n in itertools.count(2):
            raw = fh.readline(_MAX_HEADER_LINE)
            if not raw or (len(raw) == _MAX_HEADER_LINE and not raw.endswith(b"\n")):
                raise ValueError(f"{path}: PLY header has no end_header (the file is truncated or not a PLY)")
            line = raw.decode("ascii", errors="replace").rstrip("\r\n")
            words = line.split()
            if not words:
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1] if len(words) > 1 else ""
            elif words[0] == "comment":
                comments.append(line[len("comment") :].strip())
            elif words[0] == "element":
                if len(words) != 3 or not words[2].isdigit():
                    raise ValueError(f"{path}: malformed PLY header line {n}: {line!r} (expected 'element NAME "
                                     "COUNT')")
                if element is None and words[1] != "vertex":
                    raise ValueError(f"{path}: the first PLY element must be 'vertex', got {words[1]!r} (a "
                                     "compressed or non-3DGS PLY; export an uncompressed 3DGS PLY)")
                element = words[1]
                if element == "vertex":
                    count = int(words[2])
            elif words[0] == "property" and element == "vertex":
                if len(words) < 3 or words[1] == "list" or words[1] not in _PLY_TYPES:
                    raise ValueError(f"{path}: unsupported vertex property {line!r} (line {n}); a 3DGS PLY has "
                                     "scalar float properties only")
                props.append((words[2], "<" + _PLY_TYPES[words[1]]))
        offset = fh.tell()
    if fmt != "binary_little_endian":
        raise ValueError(f"{path}: only binary_little_endian PLY is supported, got format {fmt!r}; re-save it as "
                         "binary little-endian (e.g. plyfile: PlyData(..., text=False, byte_order='<'))")
    if count is None:
        raise ValueError(f"{path}: PLY has no vertex element")
    names = [name for name, _ in props]
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: duplicate vertex properties {sorted({x for x in names if names.count(x) > 1})}")
    return PlyHeader(fmt, tuple(comments), count, np.dtype(props), offset)


def load_ply(path: str | Path, *, dtype: torch.dtype = torch.float32) -> GaussianModel:
    """Read a 3DGS PLY written by :func:`save_ply` or by 3DGS-compatible tools, as stored (bit for bit; see
    :func:`load_gaussian_ply` for the checked, normalised load). Extra properties are ignored; the SH degree
    follows from the number of ``f_rest_*`` properties. A file that is no 3DGS PLY, or is truncated, raises a
    ``ValueError`` naming the file and the problem."""
    header = read_ply_header(path)
    names = set(header.vertex_dtype.names or ())
    n_rest = sum(1 for name in names if name.startswith("f_rest_"))
    valid = {3 * (num_sh_bases(d) - 1): d for d in range(4)}
    if n_rest not in valid:
        raise ValueError(f"{path}: {n_rest} f_rest_* properties; a 3DGS PLY has 0, 9, 24 or 45 of them (SH degree "
                         "0 to 3)")
    degree = valid[n_rest]
    missing = [name for name in property_names(degree) if name not in names and name not in ("nx", "ny", "nz")]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, missing properties {missing} (a 3DGS PLY has x, y, z, f_dc_0..2, "
                         "f_rest_*, opacity, scale_0..2, rot_0..3; a plain point cloud is not a Gaussian splat)")
    expected = header.vertex_count * header.vertex_dtype.itemsize
    with open(path, "rb") as fh:
        fh.seek(header.data_offset)
        data = fh.read(expected)
    if len(data) != expected:
        raise ValueError(f"{path}: truncated PLY: the header declares {header.vertex_count} Gaussians "
                         f"({expected} bytes) but the file holds {len(data)} bytes of vertex data; re-export or "
                         "re-download it")
    arr = np.frombuffer(data, dtype=header.vertex_dtype, count=header.vertex_count)
    n = header.vertex_count

    def get(cols: list[str]) -> torch.Tensor:
        stacked = np.stack([arr[c] for c in cols], axis=1) if cols else np.zeros((n, 0), dtype="<f4")
        return torch.from_numpy(np.ascontiguousarray(stacked).astype(np.float32, copy=False)).to(dtype)

    k_rest = n_rest // 3
    rest = get([f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, k_rest).transpose(1, 2).contiguous()
    return GaussianModel(
        means=get(["x", "y", "z"]),
        quats=get(["rot_0", "rot_1", "rot_2", "rot_3"]),
        log_scales=get(["scale_0", "scale_1", "scale_2"]),
        opacity_logits=get(["opacity"]).reshape(n),
        sh_dc=get(["f_dc_0", "f_dc_1", "f_dc_2"]),
        sh_rest=rest,
    )


def load_gaussian_ply(path: str | Path, *, dtype: torch.dtype = torch.float32) -> GaussianModel:
    """:func:`load_ply` for rendering a PLY from anywhere: also refuses files without Gaussians, with NaN/inf
    values or zero-norm quaternions (``ValueError`` saying how many rows), and normalises the quaternions (3DGS
    tools store them unnormalised)."""
    model = load_ply(path, dtype=dtype)
    if len(model) == 0:
        raise ValueError(f"{path}: the PLY holds zero Gaussians; nothing to render")
    bad = torch.zeros(len(model), dtype=torch.bool)
    for t in model.tensors().values():
        bad |= ~torch.isfinite(t.reshape(len(model), -1)).all(dim=1)
    if bad.any():
        rows = torch.nonzero(bad).flatten()[:5].tolist()
        raise ValueError(f"{path}: {int(bad.sum())} of {len(model)} Gaussians have NaN/inf values (rows {rows}"
                         f"{', ...' if int(bad.sum()) > 5 else ''}); the file is corrupt: re-export it or drop those "
                         "rows")
    norm = torch.linalg.vector_norm(model.quats, dim=1, keepdim=True)
    zero = norm[:, 0] < 1e-12
    if zero.any():
        rows = torch.nonzero(zero).flatten()[:5].tolist()
        raise ValueError(f"{path}: {int(zero.sum())} of {len(model)} Gaussians have a zero quaternion rot_0..3 "
                         f"(rows {rows}{', ...' if int(zero.sum()) > 5 else ''}); a rotation needs a non-zero "
                         "quaternion")
    return GaussianModel(model.means, model.quats / norm, model.log_scales, model.opacity_logits, model.sh_dc,
                         model.sh_rest)
