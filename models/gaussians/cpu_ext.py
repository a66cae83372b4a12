"""The C++ compositing kernels (``csrc/composite.cpp``): built on first use with the system's ``g++`` into a plain
shared library and called through ctypes, no torch headers (it builds in a few seconds, where a
``torch.utils.cpp_extension`` build compiles torch's headers for a minute on two cores).

The library is cached under ``<sys.prefix>/share/navcrafter/ext/`` (inside the virtualenv; ``NAVCRAFTER_EXT_DIR``
overrides it), named by the SHA-256 of the source and the flags, so an edited source rebuilds and concurrent
processes never load a half-written file (built to a temporary name, then renamed). Flags: ``-O3
-march=x86-64-v3`` (AVX2 + FMA; the CPU is checked for them at run time and the build is refused without them),
``-ffp-contract=fast`` (FMAs, as numba's ``contract``), no ``-ffast-math`` (the code compares and clamps).

:func:`load` returns the library or raises :class:`ExtensionUnavailable` with the reason and the fix; the
selection between these kernels and numba's is ``cpu_rasterize.set_kernels`` (``render.cpu_kernels``)."""
from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

SOURCE = Path(__file__).with_name("csrc") / "composite.cpp"
FLAGS = ["-O3", "-march=x86-64-v3", "-ffp-contract=fast", "-fno-math-errno", "-fopenmp-simd", "-std=c++17",
         "-shared", "-fPIC", "-pthread"]
_LOCK = threading.Lock()
_LIB: ctypes.CDLL | None = None


class ExtensionUnavailable(RuntimeError):
    """The C++ kernels cannot be built or loaded here (the message says why and how to fix it)."""


def _cpu_has_avx2_fma() -> bool:
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    for line in flags.splitlines():
        if line.startswith("flags"):
            have = set(line.split(":", 1)[1].split())
            return {"avx2", "fma", "bmi2"} <= have
    return False


def cache_dir() -> Path:
    return Path(os.environ.get("NAVCRAFTER_EXT_DIR") or Path(sys.prefix) / "share" / "navcrafter" / "ext")


def library_path() -> Path:
    digest = hashlib.sha256(SOURCE.read_bytes() + " ".join(FLAGS).encode()).hexdigest()[:16]
    return cache_dir() / f"nc_composite_{digest}.so"


def build(verbose: bool = False) -> Path:
    """Compile the library (if not cached) and return its path; raises :class:`ExtensionUnavailable`."""
    if sys.platform != "linux" or not _cpu_has_avx2_fma():
        raise ExtensionUnavailable("the C++ compositing kernels need Linux on an x86-64 CPU with AVX2 and FMA "
                                   "(x86-64-v3); use render.cpu_kernels: numba")
    out = library_path()
    if out.exists():
        return out
    cxx = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++")
    if cxx is None:
        raise ExtensionUnavailable("no C++ compiler (g++) on PATH: install one (Debian: apt-get install g++) "
                                   "or set render.cpu_kernels: numba")
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    try:
        res = subprocess.run([cxx, *FLAGS, str(SOURCE), "-o", tmp], capture_output=True, text=True)
        if res.returncode != 0:
            raise ExtensionUnavailable(f"building {SOURCE.name} with {cxx} failed:\n{res.stderr[-2000:]}")
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


_F32P = np.ctypeslib.ndpointer(np.float32, flags="C_CONTIGUOUS")
_F64P = np.ctypeslib.ndpointer(np.float64, flags="C_CONTIGUOUS")
_I64P = np.ctypeslib.ndpointer(np.int64, flags="C_CONTIGUOUS")
_I32P = np.ctypeslib.ndpointer(np.int32, flags="C_CONTIGUOUS")
_I64, _INT = ctypes.c_int64, ctypes.c_int


def load() -> ctypes.CDLL:
    """The built library with its functions' signatures (built on first use)."""
    global _LIB
    with _LOCK:
        if _LIB is None:
            lib = ctypes.CDLL(str(build()))
            for tag, fp in (("f32", _F32P), ("f64", _F64P)):
                fw = getattr(lib, f"nc_composite_forward_{tag}")
                fw.argtypes = [fp, _I64, _I64P, _I64, _I64, _I64, _I64, _I64, fp, fp, _INT, _I64, fp, fp, _I64P,
                               _I64P, _I32P, fp, fp, _INT, _INT]
                fw.restype = None
                bw = getattr(lib, f"nc_composite_backward_{tag}")
                bw.argtypes = [fp, _I64, _I64P, _I64, _I64, _I64, _I64, _I64, fp, fp, _INT, _I64, fp, fp, _I64P,
                               _I64P, _I32P, fp, fp, fp, _INT]
                bw.restype = None
            lib.nc_set_variant.argtypes = [_INT]
            _LIB = lib
        return _LIB


def _tag(dt) -> str:
    return "f32" if np.dtype(dt) == np.float32 else "f64"


def composite_forward(ent, offsets, width, height, tile_size, tile_w, cst, backgrounds, use_bg, render, t_final,
                      pbase, pend, pix, pes, pts, record, threads):
    """:func:`cpu_kernels.composite_forward`'s contract (same arrays), on ``threads`` threads."""
    fn = getattr(load(), f"nc_composite_forward_{_tag(cst.dtype)}")
    fn(ent, ent.shape[1], offsets, render.shape[0], width, height, tile_size, tile_w, cst, backgrounds,
       int(use_bg), render.shape[3], render, t_final, pbase, pend, pix, pes, pts, int(record), int(threads))


def composite_backward(ent, offsets, width, height, tile_size, tile_w, cst, backgrounds, use_bg, v_render,
                       v_alphas, pbase, pend, pix, pes, pts, slots, threads):
    """:func:`cpu_kernels.composite_backward`'s contract (same arrays), on ``threads`` threads."""
    fn = getattr(load(), f"nc_composite_backward_{_tag(cst.dtype)}")
    fn(ent, ent.shape[1], offsets, v_render.shape[0], width, height, tile_size, tile_w, cst, backgrounds,
       int(use_bg), v_render.shape[3], v_render, v_alphas, pbase, pend, pix, pes, pts, slots, int(threads))


def set_variant(v: int) -> None:
    """Experiments only (benchmarks/rasterizer_cpp.py): 0 = the plain port, 1 = the vector backward."""
    load().nc_set_variant(int(v))
