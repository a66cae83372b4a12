"""The standard 3D Gaussian Splatting PLY (as the original 3DGS code writes it; read by common splat viewers).

One ``vertex`` element, binary little-endian, all properties ``float`` (float32), in this order::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_{3(K-1)-1}  opacity  scale_0..2  rot_0..3

``f_dc_*`` are the DC SH coefficients (R, G, B); ``f_rest_*`` the higher bands in 3DGS's channel-major
order (all of red's ``K-1`` coefficients, then green's, then blue's); ``opacity`` is the logit, ``scale_*``
the log-scales, ``rot_*`` the quaternion (w, x, y, z); normals are written as zeros. Header ``comment``
lines may carry a label (navcrafter writes the simulation-mode label there). Float32 models round-trip
bit for bit.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from navcrafter.models.gaussians.model import GaussianModel
from navcrafter.models.gaussians.sh import num_sh_bases, sh_degree_from_bases

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
        if fh.readline().strip() != b"ply":
            raise ValueError(f"{path}: not a PLY file")
        fmt, comments, count, props, element = "", [], None, [], None
        while True:
            raw = fh.readline()
            if not raw:
                raise ValueError(f"{path}: PLY header has no end_header")
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
                if element is None and words[1] != "vertex":
                    raise ValueError(f"{path}: the first PLY element must be 'vertex', got {words[1]!r}")
                element = words[1]
                if element == "vertex":
                    count = int(words[2])
            elif words[0] == "property" and element == "vertex":
                if words[1] == "list" or words[1] not in _PLY_TYPES:
                    raise ValueError(f"{path}: unsupported vertex property {line!r}")
                props.append((words[2], "<" + _PLY_TYPES[words[1]]))
        offset = fh.tell()
    if fmt != "binary_little_endian":
        raise ValueError(f"{path}: only binary_little_endian PLY is supported, got format {fmt!r}")
    if count is None:
        raise ValueError(f"{path}: PLY has no vertex element")
    return PlyHeader(fmt, tuple(comments), count, np.dtype(props), offset)


def load_ply(path: str | Path, *, dtype: torch.dtype = torch.float32) -> GaussianModel:
    """Read a 3DGS PLY written by :func:`save_ply` or by 3DGS-compatible tools. Extra properties are ignored;
    the SH degree follows from the number of ``f_rest_*`` properties."""
    header = read_ply_header(path)
    names = set(header.vertex_dtype.names or ())
    n_rest = sum(1 for name in names if name.startswith("f_rest_"))
    if n_rest % 3:
        raise ValueError(f"{path}: {n_rest} f_rest properties is not a multiple of 3")
    degree = sh_degree_from_bases(n_rest // 3 + 1)
    missing = [name for name in property_names(degree) if name not in names and name not in ("nx", "ny", "nz")]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, missing properties {missing}")
    with open(path, "rb") as fh:
        fh.seek(header.data_offset)
        data = fh.read(header.vertex_count * header.vertex_dtype.itemsize)
    if len(data) != header.vertex_count * header.vertex_dtype.itemsize:
        raise ValueError(f"{path}: truncated PLY ({len(data)} bytes of vertex data)")
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
