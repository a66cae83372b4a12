"""The prepared GPU check: every CUDA measurement the project still owes, as one command on one GPU in < 8 minutes.

On a bare, air-gapped CUDA node (the project's folder copied there, not installed) run it through
``deploy/gpu/run_check.sh`` (deploy/gpu/README.md): it brings the missing wheels, makes ``navcrafter`` importable,
builds gsplat in a capped step of its own and runs this under a deadline. Directly, where navcrafter is installed:

    python benchmarks/gpu_check.py --out bench-out/gpu-check            # ~6.5 min at most (per-item time caps)
    python benchmarks/gpu_check.py --out bench-out/gpu-check --quick    # ~5 min at most, smaller sizes
    python benchmarks/gpu_check.py --preflight [--out DIR]              # what the node has; exit 3 with the reasons
    python benchmarks/gpu_check.py --build-gsplat [--out DIR]           # gsplat's JIT build (resumable), run capped
    python benchmarks/gpu_check.py --out bench-out/gpu-check --items dit,dit-onnx   # + the opt-in ONNX export
    python benchmarks/gpu_check.py --out bench-out/gpu-check --prepare-scene-models   # once, any machine
    python benchmarks/gpu_check.py --out bench-out/gpu-check --with-explore           # + the whole flow

Random weights everywhere (timing, memory and precision only; no quality). Items, each in its own subprocess with
its own time cap (a failure, a crash, a failed import or a timeout of one is recorded and the next one runs);
``results.json`` / ``results.md`` are rewritten after every item, so a crash or a kill keeps what was measured:

* ``gsplat``: ``benchmarks/gsplat_fit.py``'s ``run`` (its quick size): iterations/s of the gsplat-backed fit,
  first-call time, parity of our renderer vs gsplat. gsplat JIT-builds its CUDA kernels on first use (minutes):
  that build is never inside this item's cap (``--build-gsplat``, which run_check.sh caps); unbuilt, the item is
  ``not built`` with the reason; skipped with its reason without CUDA.
* ``dit``: one denoising step (CFG pair) of the camera-controlled Wan DiT at Wan2.1-1.3B width, 81 frames at
  256² (``benchmarks/synthesis.py``'s ``build``/``make_inputs``), torch bf16: step time and peak memory
  (``torch.cuda.max_memory_allocated``).
* ``fun-camera``: the Fun-Camera DiT (``navcrafter.models.synthesis.funcamera``, 1.3B config, same latent grid)
  the same way; ``not built`` only if that module is absent from the tree, a failed import otherwise.
* ``vggt``: VGGT-1B (``models/geometry/vggt/``, full config) on 25 frames at 518², bf16 autocast.
* ``moge``: MoGe-2 ViT-L (normal) at 518² (1,369 tokens), bf16 autocast.
* ``difix``: the Difix refiner (SD-Turbo size, reference mixing) at 512², fp16.
* ``training``: one camera-control training step + one sampling step at 1.3B width
  (``benchmarks/camera_training_gpu.py``'s ``main``).
* ``scene``: one scene at the paper's settings (N=3 iterations, 81 × 256² clips, 40 DPM-solver steps with CFG):
  the learned-model time composed from the items above (N × steps × DiT step, VGGT per lift scaled to
  ``lift.max_views`` + 1 frames, MoGe, fit iterations / gsplat it/s), compared with the paper's 4.79 min per scene
  (Table V). With ``--with-explore`` (beyond the 8 minutes: cap 600 s) also the whole ``explore`` flow with
  ``--backend onnx`` on tiny random-weight models exported at the paper's clip size: the time of everything that
  is not a learned model at full size (planning, lifting, the fit, the store, Prefect). Exporting those models
  takes long even though they are tiny (the Wan VAE graphs unroll 81 frames; ``export-all --preset paper``: 19 min
  wall, 9 min CPU on a shared 2-core machine, 2026-12-02), so it is a separate step that also runs on a CPU machine
  and resumes role by role: ``--prepare-scene-models`` (into ``--scene-models DIR``, default
  ``WORK/scene-models``). That explore path was checked once on the CPU (2 shared cores, onnxruntime CPU, fit on
  the CPU): the room demo scene finished in 4.3 min (plumbing only, not a GPU number).
* opt-in ``dit-onnx`` / ``fun-camera-onnx`` (named in ``--items``; own caps): the same modules exported to ONNX
  (fp32 ``onnxio.export_graph``, then ``onnxio.convert_graph_fp16`` as ``navcrafter models convert-fp16`` does:
  fp32 normalisations and IO), export and conversion timed; then, where onnxruntime has the CUDA execution provider
  (``onnxruntime-gpu``), the fp16 graph timed against bf16 torch (NVML process memory, output difference). The CUDA
  image's onnxruntime is a CPU build and onnxruntime-gpu (~256 MB) cannot travel: there ORT is reported skipped.

``--deadline EPOCH`` cuts every cap to the time left and marks items past it ``not run``; ``--keep`` merges a
rerun of some items into an earlier results.json; ``--work DIR`` keeps scratch (partials, ONNX files) out of
``--out``. results.md ends with what did not run on the node, and why. Refuses without CUDA (exit code 2).
``--device cpu --dry-run`` runs the plumbing with tiny configs on the CPU for the tests: its numbers are NOT
measurements and every output says so.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
if __package__ in (None, ""):  # run as a script: the repository root makes the benchmarks package importable
    sys.path.insert(0, str(HERE.parent))
PAPER_SCENE_MIN = 4.79  # NavCrafter, Table V: minutes per scene
DRY_RUN_LABEL = "DRY RUN (CPU, tiny configs): plumbing only, NOT a measurement"
EXPLORE_CAP = 600  # --with-explore: the scene item's cap (beyond the 8-minute budget)

# name -> (full cap s, quick cap s), each sized for what the item does on one GPU once gsplat is built (estimates: no
# GPU was lent to measure them): a fresh process importing torch, diffusers and transformers (~10 s), building the
# module with random weights on the GPU, a warm-up and 2-3 timed calls. The full caps sum to 390 s, the quick ones to
# 290 s. gsplat's JIT build is never inside an item: it is its own step (``--build-gsplat``, run_check.sh caps it),
# and the gsplat item reports ``not built`` without it. What an item measured before its cap is kept ("partial").
ITEMS: dict[str, tuple[int, int]] = {
    "gsplat": (60, 45), "dit": (60, 45), "fun-camera": (60, 45), "vggt": (45, 30), "moge": (30, 25),
    "difix": (30, 25), "training": (90, 60), "scene": (15, 15),
}
# opt-in (named in --items): the ONNX export of the 1.3B-width DiTs (dynamo export + onnxscript's optimiser, then the
# fp16 conversion: minutes of CPU work on one core, so never inside the default items), and onnxruntime on the
# product's fp16 graph where a CUDA execution provider exists. The image's onnxruntime is a CPU build and
# onnxruntime-gpu (~256 MB) cannot travel in 64 MiB: there these items time the export and say that ORT did not run.
OPT_IN: dict[str, tuple[int, int]] = {"dit-onnx": (300, 240), "fun-camera-onnx": (240, 180),
                                      "camera-mini": (420, 240)}
# camera-mini (opt-in; issue 32 item 4): benchmarks/camera_control_mini.py at Wan2.1-1.3B width on the GPU, trained
# from scratch for a few hundred steps per stage and measured as camera control on held-out clips. The node has no
# open3d (the simulator's ray caster), so the scenes are rendered beforehand on a machine that has it
# (``--prepare-camera-scenes``, into CAMERA_SCENES, git-ignored) and carried with the tree. Measured 2026-12-04 on an
# H200: 0.31 s per base step, 0.25-0.31 s per control step at this size (400 + 400 steps in 254 s incl. start-up).
CAMERA_SCENES = HERE.parent / "deploy" / "gpu" / "scenes"
CAMERA_MINI_DATA = ["--resolution", "64", "--frames", "17", "--autoencoder", "exact", "--train-scenes", "6",
                    "--eval-scenes", "3"]
# Wan2.1-1.3B as it is: its (1, 2, 2) patch too (the CPU miniature uses patch 1)
CAMERA_MINI_WIDTH = ["--patch", "2", "--heads", "12", "--head-dim", "128", "--layers", "30", "--ffn", "8960",
                     "--adapter-channels", "64"]
CAMERA_MINI_STEPS = {"full": (400, 200), "quick": (150, 50)}  # steps per stage, warmup
# held-out clips per sampling call. 2026-12-04 (second lease): one clip at a time, the trained, untrained, mirrored
# and unguided conditions (6 DiT calls per step with camera guidance, 20 steps, 24 clips) did not finish within the
# 420 s cap after ~255 s of training; a GPU samples the 24 clips of a condition in one batch
CAMERA_MINI_SAMPLE_BATCH = 24
# the dry run's plumbing sizes (CPU, tiny): its own scenes file
CAMERA_MINI_DRY = (["--resolution", "32", "--frames", "5", "--autoencoder", "exact", "--train-scenes", "1",
                    "--eval-scenes", "1"],
                   ["--heads", "2", "--head-dim", "16", "--layers", "1", "--ffn", "32", "--adapter-channels", "8"],
                   (2, 1))
CAPS = ITEMS | OPT_IN
MIN_ITEM_S = 10  # with --deadline: an item that would get less than this is "not run" (out of time)
GSPLAT_EXT = "gsplat_cuda"  # the name gsplat 1.5 JIT-builds its kernels under (gsplat/cuda/_backend.py)


def _bench_import(name: str):
    """A sibling benchmark module, ``benchmarks.<name>`` (imported when an item needs it)."""
    import importlib

    return importlib.import_module(f"benchmarks.{name}")


# --------------------------------------------------------------------------------------------------
# Timing helpers
# --------------------------------------------------------------------------------------------------
def _sync(device: str) -> None:
    import torch

    if device == "cuda":
        torch.cuda.synchronize()


def timed(fn, device: str, repeats: int, warmup: int = 1) -> dict:
    """Median/min seconds of ``fn()`` over ``repeats`` after ``warmup`` calls, and the peak memory (CUDA)."""
    import statistics

    import torch

    if device == "meta":  # shape check only
        repeats, warmup = 1, 0
    for _ in range(warmup):
        fn()
    _sync(device)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    out = {"median_s": statistics.median(times), "min_s": min(times), "repeats": repeats}
    if device == "cuda":
        out["peak_gib"] = torch.cuda.max_memory_allocated() / 2**30
    return out


def _free(device: str) -> None:
    import gc

    import torch

    gc.collect()
    if device == "cuda":
        torch.cuda.empty_cache()


def _autocast(device: str):
    """bf16 autocast on CUDA; nothing elsewhere (the CPU dry run, the meta-device shape check)."""
    import contextlib

    import torch

    return torch.autocast("cuda", dtype=torch.bfloat16) if device == "cuda" else contextlib.nullcontext()


def save_partial(ctx: dict, res: dict) -> None:
    """What an item has measured so far, read back by the parent if the item times out or crashes later."""
    if ctx.get("partial"):
        Path(ctx["partial"]).write_text(json.dumps(res, default=str))


def _max_rel(a, b) -> float:
    import numpy as np

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-12))


# --------------------------------------------------------------------------------------------------
# Items (each runs in its own process; ctx: device, dry_run, quick, work)
# --------------------------------------------------------------------------------------------------
def gsplat_state() -> dict:
    """Whether gsplat is installed and its CUDA kernels are built, without importing ``gsplat.cuda._backend`` (whose
    import starts the JIT build): a prebuilt ``gsplat/csrc*.so``, or ``gsplat_cuda.so`` in torch's extension build
    folder (``TORCH_EXTENSIONS_DIR``, which run_check.sh points at its cache)."""
    import importlib.util

    try:
        spec = importlib.util.find_spec("gsplat")
    except (ImportError, ValueError) as exc:
        spec, why = None, f"{type(exc).__name__}: {exc}"
    else:
        why = "gsplat is not installed (carry its wheel: deploy/gpu/wheels.txt)"
    if spec is None or not spec.origin:
        return {"installed": False, "built": False, "reason": why}
    pkg = Path(spec.origin).parent
    state = {"installed": True, "path": str(pkg)}
    if prebuilt := sorted(pkg.glob("csrc*.so")):
        return state | {"built": True, "library": str(prebuilt[0])}
    try:
        from torch.utils.cpp_extension import _get_build_directory

        build = Path(_get_build_directory(GSPLAT_EXT, verbose=False))
    except Exception as exc:  # a private torch helper: say so if it moved
        return state | {"built": False, "reason": f"torch's extension folder is unknown ({type(exc).__name__}: {exc})"}
    lib = build / f"{GSPLAT_EXT}.so"
    state.update(build_dir=str(build), library=str(lib), built=lib.is_file())
    if not state["built"]:
        state["reason"] = (f"gsplat's CUDA kernels are not built ({lib} missing): build them first in their own "
                           "capped step (`gpu_check.py --build-gsplat`, run_check.sh does it); never inside an item")
    return state


def gsplat_build_env() -> None:
    """``TORCH_CUDA_ARCH_LIST`` = this device's compute capability (e.g. ``9.0``) unless set, and ``MAX_JOBS`` = the CPU
    count. The build step and the gsplat item must agree: torch's JIT writes the architecture flags into the ninja
    file, and without the variable it picks ``9.0+PTX`` for the visible card, a different command line, so ninja
    would rebuild every kernel inside the item's cap."""
    import torch

    major, minor = torch.cuda.get_device_capability(0)
    os.environ.setdefault("TORCH_CUDA_ARCH_LIST", f"{major}.{minor}")
    os.environ.setdefault("MAX_JOBS", str(os.cpu_count() or 1))


def build_gsplat() -> dict:
    """gsplat's own JIT build (``import gsplat.cuda._backend``, its flags and sources), for this device's compute
    capability only, with ``MAX_JOBS`` = the CPU count; resumable: gsplat deletes its build folder before a fresh
    build, which would throw away the objects a killed build left, so that one deletion is skipped here and ninja
    goes on from them. Run it under a time cap (run_check.sh: ``timeout``); a second run finishes a cut one."""
    import shutil

    import torch

    state = gsplat_state()
    if state.get("built"):
        return state | {"status": "ok", "note": "already built"}
    if not state["installed"]:
        return state | {"status": "error"}
    if not torch.cuda.is_available():
        return state | {"status": "skipped", "reason": "no CUDA device: gsplat's kernels are built for the device"}
    gsplat_build_env()
    build, rmtree = Path(state["build_dir"]).resolve(), shutil.rmtree

    def keep_objects(path, *args, **kwargs):
        if Path(path).resolve() == build:
            return None
        return rmtree(path, *args, **kwargs)

    t0 = time.perf_counter()
    shutil.rmtree = keep_objects
    try:
        from gsplat.cuda._backend import _C
    finally:
        shutil.rmtree = rmtree
    res = gsplat_state() | {"seconds": time.perf_counter() - t0, "arch": os.environ["TORCH_CUDA_ARCH_LIST"],
                            "max_jobs": os.environ["MAX_JOBS"]}
    if _C is None:
        return res | {"status": "error", "reason": "gsplat found no CUDA toolkit (nvcc) and built nothing"}
    return res | {"status": "ok" if res["built"] else "error"}


def item_gsplat(ctx: dict) -> dict:
    state = gsplat_state()
    if ctx["device"] == "cuda" and not state.get("built"):  # its JIT build would not fit an item's cap
        return {"status": "not built", "reason": state["reason"], "gsplat": state}
    g = _bench_import("gsplat_fit")
    why = g.refuse_without_cuda()
    if why:
        return {"status": "skipped", "reason": why}
    gsplat_build_env()  # the build step's flags: loading the built kernels then compiles nothing
    ns = argparse.Namespace(quick=True, gaussians=100_000 if not ctx["quick"] else 50_000, size=128, views=8,
                            iterations=100 if not ctx["quick"] else 60, torch_iterations=3, densify=False)
    r = g.run(ns)
    r["markdown"] = g.markdown(r)
    return {"status": "ok", **r}  # gsplat_fit.run reports no status of its own (the 2026-12-04 H200 run read None)


def _ort_session(path: Path, device: str):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    providers = ["CUDAExecutionProvider", "CPUExecutionProvider"] if device == "cuda" else ["CPUExecutionProvider"]
    return ort.InferenceSession(str(path), sess_options=opts, providers=providers)


def _ort_timed(sess, feeds: dict, device: str, repeats: int) -> dict:
    import statistics

    syn = _bench_import("synthesis")
    sess.run(None, feeds)  # warm-up (CUDA EP allocates its arena here)
    nvml = syn._NvmlPeak() if device == "cuda" else syn._Null()
    times = []
    with nvml:
        for _ in range(repeats):
            t0 = time.perf_counter()
            out = sess.run(None, feeds)[0]
            times.append(time.perf_counter() - t0)
    res = {"median_s": statistics.median(times), "min_s": min(times), "repeats": repeats,
           "providers": sess.get_providers()}
    if device == "cuda":
        res["peak_gib"] = (nvml.peak / 1024) if getattr(nvml, "peak", None) else None
        res["memory_kind"] = "NVML process memory (peak of 5 ms samples)" if res["peak_gib"] else "unavailable"
    return res, out


def _torch_vs_ort(make_module, inputs: dict, names: list[str], outputs: list[str], ctx: dict, tag: str,
                  meta: dict) -> dict:
    """One module (``make_module()``; built here so that no caller keeps it alive while onnxruntime runs): torch
    (bf16 on CUDA, fp32 in a dry run) timing; with ``ctx["onnx"]`` (the opt-in ``*-onnx`` items) then an ONNX export
    of the same weights on ORT: on CUDA the product's fp16 path (an fp32 export converted by
    ``onnxio.convert_graph_fp16``, as ``navcrafter models convert-fp16`` does: fp16 with fp32 normalisations and
    inputs/outputs), in a dry run the fp32 export. Without a CUDA execution provider the graph is exported and
    converted (timed) and onnxruntime is reported as skipped, with the reason."""
    import torch

    device, repeats = ctx["device"], 2 if ctx["quick"] or ctx["dry_run"] else 3
    tdtype = torch.bfloat16 if device == "cuda" else torch.float32
    half = device == "cuda"
    res: dict = {**meta, "torch_dtype": str(tdtype).split(".")[-1],
                 "onnx_dtype": "float16 (convert-fp16: fp32 norms and IO)" if half else "float32"}

    def cast(dtype):
        return [inputs[n].to(device=device, dtype=dtype) if inputs[n].is_floating_point() else inputs[n].to(device)
                for n in names]

    holder = {"module": make_module().to(device=device, dtype=tdtype).eval(), "args": cast(tdtype)}
    if device == "meta":  # the tests' shape check of the full-size configs: one forward, nothing timed or exported
        with torch.no_grad():
            out = holder["module"](*holder["args"])
        out = out[0] if isinstance(out, (tuple, list)) else out
        return res | {"status": "ok", "output_shape": list(out.shape)}
    with torch.no_grad():
        res["torch"] = timed(lambda: holder["module"](*holder["args"]), device, repeats)
        ref = holder["module"](*holder["args"])
    ref = (ref[0] if isinstance(ref, (tuple, list)) else ref).float().cpu().numpy()
    save_partial(ctx, res)
    if not ctx.get("onnx"):
        res["status"] = "ok"
        res["ort"] = {"status": "not run", "reason": f"the ONNX export and onnxruntime are the opt-in item "
                      f"{tag.replace('_', '-')}-onnx (--items ...,{tag.replace('_', '-')}-onnx)"}
        return res
    no_ep = None
    if device == "cuda":
        import onnxruntime

        if "CUDAExecutionProvider" not in onnxruntime.get_available_providers():
            no_ep = (f"onnxruntime {onnxruntime.__version__} has no CUDA execution provider here (a CPU build; "
                     "onnxruntime-gpu matching the CUDA version is needed, ~256 MB, too big to carry): the graph was "
                     "exported and converted, not run")
    from navcrafter.models.runtime.onnxio import convert_graph_fp16, export_graph

    holder["module"] = holder["module"].to(dtype=torch.float32)
    holder["args"] = cast(torch.float32)
    path = Path(ctx["work"]) / f"{tag}.onnx"
    t0 = time.perf_counter()
    export_graph(holder["module"], tuple(holder["args"]), path, input_names=names, output_names=outputs)
    res["export_s"] = time.perf_counter() - t0
    save_partial(ctx, res)
    if half:
        holder["module"] = None  # the weights leave the GPU while the graph is converted on the CPU
        _free(device)
        t0 = time.perf_counter()
        path = Path(ctx["work"]) / convert_graph_fp16(path, path.with_name(f"{tag}.fp16.onnx")).file
        res["convert_fp16_s"] = time.perf_counter() - t0
        save_partial(ctx, res)
    if no_ep:
        res["status"] = "ok"
        res["ort"] = {"status": "skipped", "reason": no_ep}
        return res
    feeds = {n: a.cpu().numpy() for n, a in zip(names, holder["args"])}
    holder.clear()
    _free(device)
    t0 = time.perf_counter()
    sess = _ort_session(path, device)
    res["ort_load_s"] = time.perf_counter() - t0
    res["ort"], out = _ort_timed(sess, feeds, device, repeats)
    res["ort_vs_torch_max_rel_diff"] = _max_rel(out, ref)
    res["ort_over_torch"] = res["ort"]["median_s"] / res["torch"]["median_s"]
    res["status"] = "ok"
    return res


def item_dit(ctx: dict) -> dict:
    import torch

    syn = _bench_import("synthesis")
    from navcrafter.models.synthesis.camcontrol import DIT_OUTPUTS

    config, frames, size = ("tiny", 5, 32) if ctx["dry_run"] else ("wan-1.3b", 81, 256)
    inputs = {k: torch.as_tensor(v) for k, v in syn.make_inputs(config, frames, size).items()}
    dev = "cpu" if ctx["dry_run"] else ctx["device"]

    def make():
        if dev == "meta":  # build() gives the zero-initialised control random values, which needs real tensors
            from navcrafter.models.synthesis.camcontrol import build_camera_wan

            return syn._camera_graph(build_camera_wan(*syn.model_configs(config), device="meta"))
        return syn._camera_graph(syn.build(config, "camera", device=dev))

    res = _torch_vs_ort(make, inputs,
                        list(syn.CAMERA_INPUTS), list(DIT_OUTPUTS), ctx, "dit",
                        {"config": config, "frames": frames, "size": size, "batch": 2,
                         "what": "one DiT call on the CFG pair"})
    return res


def item_fun_camera(ctx: dict) -> dict:
    import importlib

    name = "navcrafter.models.synthesis.funcamera"
    try:
        mod = importlib.import_module(name)
    except ModuleNotFoundError as exc:
        if exc.name != name:  # navcrafter itself, or a dependency: a failed import, reported as one
            raise
        return {"status": "not built", "reason": f"{name} does not exist in this tree"}
    needed = ("FunCameraConfig", "build_fun_camera", "fun_example_inputs", "FUN_DIT_INPUTS", "FUN_DIT_OUTPUTS")
    if lacking := [n for n in needed if not hasattr(mod, n)]:
        return {"status": "not built", "reason": f"{name} imports but lacks {', '.join(lacking)}"}
    wrapper = getattr(importlib.import_module(f"{name}.export"), "_FunExportWrapper", None)  # the graph's wrapper
    if wrapper is None:
        return {"status": "not built", "reason": f"{name}.export imports but lacks _FunExportWrapper"}
    config = mod.FunCameraConfig.tiny() if ctx["dry_run"] else mod.FunCameraConfig.wan_1_3b()
    # latent grid of 81 frames at 256² (dry run: 5 frames at 32²... in tiny latents), batch 2 (the CFG pair)
    shape = (2, 2, 4, 4) if ctx["dry_run"] else (2, 21, 32, 32)
    dev = "cpu" if ctx["dry_run"] else ctx["device"]
    box = [mod.build_fun_camera(config, device=dev)]
    inputs = {k: v.float() for k, v in mod.fun_example_inputs(box[0], shape).items()}
    names = list(mod.FUN_DIT_INPUTS)
    return _torch_vs_ort(lambda: wrapper(box.pop()), inputs, names, list(mod.FUN_DIT_OUTPUTS), ctx,
                         "fun_camera", {"config": "tiny" if ctx["dry_run"] else "wan-1.3b", "latent_shape": list(shape),
                                        "what": "one Fun-Camera DiT call on the CFG pair"})


def item_vggt(ctx: dict) -> dict:
    import torch

    from navcrafter.models.geometry.vggt import VGGT, VGGTConfig

    device = ctx["device"]
    if ctx["dry_run"]:
        config, frames, size = VGGTConfig.tiny(), 2, 56
    else:
        config, frames, size = VGGTConfig.vggt_1b(), (8 if ctx["quick"] else 25), 518
    torch.manual_seed(0)
    with torch.device(device):  # initialised where it runs (1B parameters: seconds on a GPU, not on a CPU core)
        model = VGGT(config).eval()
    images = torch.rand(1, frames, 3, size, size, device=device)

    @torch.no_grad()
    def step():
        with _autocast(device):
            return model(images)

    res = timed(step, device, 2 if ctx["quick"] else 3)
    res.update({"status": "ok", "frames": frames, "size": size, "dtype": "bf16 autocast" if device == "cuda"
                else "fp32", "parameters": sum(p.numel() for p in model.parameters())})
    return res


def item_moge(ctx: dict) -> dict:
    import torch

    from navcrafter.models.geometry.moge import MoGe2, MoGe2Config

    device = ctx["device"]
    config, size = (MoGe2Config.tiny(), (42, 56)) if ctx["dry_run"] else (MoGe2Config.vitl_normal(), (518, 518))
    torch.manual_seed(0)
    with torch.device(device):
        model = MoGe2(config).eval()
    image = torch.rand(1, 3, *size, device=device)

    @torch.no_grad()
    def step():
        with _autocast(device):
            return model(image)

    res = timed(step, device, 3)
    res.update({"status": "ok", "size": list(size), "tokens": (size[0] // 14) * (size[1] // 14),
                "parameters": sum(p.numel() for p in model.parameters())})
    return res


def item_difix(ctx: dict) -> dict:
    import torch

    from navcrafter.models.refiner.difix import DifixConfig, DifixRefinerModel

    device = ctx["device"]
    config = DifixConfig.tiny(True) if ctx["dry_run"] else DifixConfig.sd_turbo(True)
    size = 64 if ctx["dry_run"] else 512
    dtype = torch.float16 if device == "cuda" else torch.float32
    torch.manual_seed(0)
    with torch.device(device):
        model = DifixRefinerModel(config).to(dtype=dtype).eval()
    image = torch.rand(1, 3, size, size, device=device, dtype=dtype) * 2 - 1
    prompt = torch.randn(1, config.text_tokens, config.cross_attention_dim, device=device, dtype=dtype)
    f = config.vae_scale_factor
    noise = torch.randn(1, config.num_views, config.latent_channels, size // f, size // f, device=device, dtype=dtype)

    @torch.no_grad()
    def step():
        return model(image, image, prompt, noise)

    res = timed(step, device, 3)
    res.update({"status": "ok", "size": size, "dtype": str(dtype).split(".")[-1], "reference_mixing": True,
                "parameters": sum(p.numel() for p in model.parameters())})
    return res


def item_training(ctx: dict) -> dict:
    if ctx["device"] != "cuda":
        return {"status": "skipped", "reason": "camera_training_gpu.py is CUDA-only (dry-run)"}
    ctg = _bench_import("camera_training_gpu")
    out = Path(ctx["work"]) / "camera-training-gpu"
    rc = ctg.main(["--out", str(out), "--repeats", "1" if ctx["quick"] else "2"])
    if rc != 0:
        return {"status": "error", "error": f"camera_training_gpu.main returned {rc}"}
    res = json.loads((out / "results.json").read_text())
    res["status"] = "ok"
    return res


def scene_models(ctx: dict) -> Path:
    return Path(ctx.get("scene_models") or Path(ctx["work"]) / "scene-models")


def _navcrafter() -> list[str]:
    nav = Path(sys.executable).parent / "navcrafter"  # the console script of this environment
    if nav.exists():
        return [str(nav)]
    return [sys.executable, "-c", "import sys; from navcrafter.flows.cli import main; sys.exit(main())"]


def prepare_scene_models(models: Path, deadline: float | None = None) -> dict:
    """Tiny random-weight models exported at the paper's clip size, one role at a time (a finished role is kept:
    an interrupted preparation resumes). CPU is enough; ~20 min on 2 cores (the VAE graphs unroll 81 frames)."""
    s = paper_settings()["synthesis"]
    out = {}
    roles = {"synthesizer": ["export-synthesizer", "--frames", str(s["num_frames"]), "--height", str(s["height"]),
                             "--width", str(s["width"])],
             "geometry": ["export-geometry"], "monodepth": ["export-monodepth"]}
    for role, args in roles.items():
        if (models / role / "manifest.json").is_file():
            out[role] = "reused"
            continue
        left = None if deadline is None else deadline - time.time()
        if left is not None and left < 5:
            raise TimeoutError(f"no time left to export {role}")
        t0 = time.perf_counter()
        p = run_group(_navcrafter() + ["models", *args, str(models / role), "--random", "tiny"], left or 1e9)
        if p.returncode != 0:
            raise RuntimeError(f"export of {role} exited {p.returncode}: {(p.stderr or p.stdout)[-1500:]}")
        out[role] = time.perf_counter() - t0
    return out


def _scene_explore(ctx: dict, deadline: float) -> dict:
    """The explore flow, backend onnx, on the prepared tiny random-weight models (paper clip size)."""
    work, models = Path(ctx["work"]), scene_models(ctx)
    photos, store = work / "scene-photos", work / "scene-store"
    res: dict = {"models": str(models), "export_s": prepare_scene_models(models, deadline)}
    if not photos.is_dir():
        run_group(_navcrafter() + ["demo-data", str(photos), "--kinds", "room"], 120)
    left = deadline - time.time()
    if left < 5:
        raise TimeoutError("no time left for explore")
    t0 = time.perf_counter()
    p = run_group(_navcrafter() + ["explore", str(photos), "--store", str(store), "--backend", "onnx", "--models",
                                   str(models)], left)
    if p.returncode != 0:
        raise RuntimeError(f"explore exited {p.returncode}: {(p.stderr or p.stdout)[-1500:]}")
    res["explore_s"] = time.perf_counter() - t0
    res["explore_min"] = res["explore_s"] / 60
    res["what"] = ("whole explore flow, paper preset, tiny random-weight models at the paper's clip size: the "
                   "non-learned parts at full size (planning, lifting, the fit, the store, orchestration)")
    return res


def paper_settings() -> dict:
    """The paper preset's numbers that the scene composition and the explore models use (schemas layer: pydantic
    and yaml, no CLI)."""
    from navcrafter.schemas.config import RunConfig

    cfg = RunConfig.load(None, preset="paper")
    return {"iterations": cfg.iterations, "synthesis": {"steps": cfg.synthesis.steps,
                                                        "num_frames": cfg.synthesis.num_frames,
                                                        "height": cfg.synthesis.height, "width": cfg.synthesis.width},
            "lift_max_views": cfg.lift.max_views, "fit_iterations": cfg.fit.iterations}


def item_scene(ctx: dict) -> dict:
    res: dict = {"status": "ok", "paper_min_per_scene": PAPER_SCENE_MIN, "paper_settings": paper_settings()}
    if ctx["dry_run"]:
        res["explore"] = {"status": "not run in a dry run"}
        return res
    if not ctx.get("with_explore"):
        res["explore"] = {"status": "not run", "reason": "pass --with-explore (after --prepare-scene-models) to "
                                                         "time the whole flow as well (beyond the 8-minute budget)"}
        return res
    import importlib.util

    if lacking := [m for m in ("prefect", "zarr", "open3d") if importlib.util.find_spec(m) is None]:
        res["explore"] = {"status": "skipped", "reason": f"the explore flow needs {', '.join(lacking)}, not "
                          "installed here (not on the air-gapped CUDA image, and too big to carry: open3d alone is "
                          "~900 MB installed); the learned-model time above is composed without it"}
        return res
    deadline = time.time() + ctx["cap"] - 5
    try:
        res["explore"] = _scene_explore(ctx, deadline) | {"status": "ok"}
    except (subprocess.TimeoutExpired, TimeoutError) as exc:
        res["explore"] = {"status": "timeout", "reason": f"did not finish in the item's cap ({exc}); finished "
                                                         f"exports are kept and reused"}
    except Exception as exc:  # recorded, not fatal
        res["explore"] = {"status": "error", "error": f"{type(exc).__name__}: {exc}"[-2000:]}
    return res


def compose_scene(results: dict) -> dict:
    """Learned-model time of one paper-settings scene from the measured items (a lower bound: VAE encode/decode,
    CLIP image encoding and data movement are not measured here). Pure arithmetic on the results (the paper
    settings come from the scene item's own process), so it cannot fail on an import in the parent."""
    cfg = results["scene"]["paper_settings"]
    n, steps, frames = cfg["iterations"], cfg["synthesis"]["steps"], cfg["lift_max_views"] + 1
    terms, missing = {}, []
    dit = results.get("dit", {})
    dit = dit if dit.get("status") == "ok" else dit.get("partial", {})  # torch timed before a later failure
    if "torch" in dit:
        terms["dit"] = n * steps * dit["torch"]["median_s"]
    else:
        missing.append("dit")
    vggt = results.get("vggt", {})
    if vggt.get("status") == "ok":
        # attention is global over frames: scale the measured frame count linearly (an underestimate for more)
        terms["vggt"] = (1 + n) * vggt["median_s"] * frames / vggt["frames"]
    else:
        missing.append("vggt")
    moge = results.get("moge", {})
    if moge.get("status") == "ok":
        terms["moge"] = moge["median_s"]
    else:
        missing.append("moge")
    gs = results.get("gsplat", {})
    if gs.get("gsplat_fit"):
        terms["fit"] = cfg["fit_iterations"] / gs["gsplat_fit"]["its_per_s"]
    else:
        missing.append("fit (gsplat)")
    total = sum(terms.values())
    return {"iterations": n, "steps": steps, "geometry_frames_per_lift": frames, "terms_s": terms,
            "total_s": total, "total_min": total / 60, "over_paper": (total / 60) / PAPER_SCENE_MIN,
            "missing": missing, "dit_width": dit.get("config")}


def camera_mini_args(dry_run: bool) -> tuple[list[str], list[str], Path]:
    """The camera-mini item's data options, width options and scenes file (the dry run's are tiny)."""
    if dry_run:
        return CAMERA_MINI_DRY[0], CAMERA_MINI_DRY[1], CAMERA_SCENES / "camera-mini-dry.pkl"
    return CAMERA_MINI_DATA, CAMERA_MINI_WIDTH, CAMERA_SCENES / "camera-mini.pkl"


def prepare_camera_scenes(dry_run: bool, scenes: Path | None = None) -> dict:
    """Render the camera-mini item's scenes into its file (a machine with open3d; CPU, about a minute)."""
    data, _, path = camera_mini_args(dry_run)
    path = scenes or path
    mini = _bench_import("camera_control_mini")
    t0 = time.perf_counter()
    rc = mini.main(["--out", str(path.parent / "render-log"), "--scenes", str(path), "--render-only", *data])
    if rc != 0 or not path.is_file():
        raise RuntimeError(f"camera_control_mini --render-only returned {rc} and wrote no {path}")
    return {"scenes": str(path), "bytes": path.stat().st_size, "seconds": time.perf_counter() - t0}


def item_camera_mini(ctx: dict) -> dict:
    data, width, path = camera_mini_args(ctx["dry_run"])
    path = Path(ctx.get("camera_scenes") or path)
    if not path.is_file():
        return {"status": "not built", "reason": f"no rendered scenes at {path}: render them where open3d is "
                f"(`python benchmarks/gpu_check.py --prepare-camera-scenes`{' --dry-run' if ctx['dry_run'] else ''})"
                " and carry deploy/gpu/scenes/ with the tree"}
    mini = _bench_import("camera_control_mini")
    steps, warmup = CAMERA_MINI_DRY[2] if ctx["dry_run"] else CAMERA_MINI_STEPS["quick" if ctx["quick"] else "full"]
    out = Path(ctx["work"]) / "camera-mini"
    argv = ["--out", str(out), "--device", ctx["device"], "--scenes", str(path), "--threads",
            str(min(8, os.cpu_count() or 1)), "--base-steps", str(steps), "--control-steps", str(steps),
            "--warmup", str(warmup), "--sample-batch", str(CAMERA_MINI_SAMPLE_BATCH), *data, *width]
    if ctx.get("partial"):  # each finished stage lands there: a run cut by its cap still reports what it measured
        argv += ["--progress", ctx["partial"]]
    rc = mini.main(argv)
    if rc != 0:
        return {"status": "error", "error": f"camera_control_mini.main returned {rc}", "argv": argv}
    r = json.loads((out / "results.json").read_text())
    keys = ("direction_accuracy", "direction_accuracy_se", "r_err", "t_err", "psnr", "ssim", "camera_gap",
            "camera_gap_se")
    res = {"status": "ok", "argv": argv, "floor": {k: r["floor"][k] for k in ("r_err", "t_err")},
           "autoencoder_psnr": r["autoencoder_psnr"], "setup": r["setup"]}
    for name in ("trained", "untrained", "trained_wrong_cameras"):
        res[name] = {k: r[name].get(k) for k in keys}
    if ctx.get("out") and (out / "turns.png").is_file():  # the picture comes back with the results
        shutil.copyfile(out / "turns.png", Path(ctx["out"]) / "camera-mini-turns.png")
    return res


def item_dit_onnx(ctx: dict) -> dict:
    return item_dit(dict(ctx, onnx=True))


def item_fun_camera_onnx(ctx: dict) -> dict:
    return item_fun_camera(dict(ctx, onnx=True))


FUNCS = {"gsplat": item_gsplat, "dit": item_dit, "fun-camera": item_fun_camera, "vggt": item_vggt,
         "moge": item_moge, "difix": item_difix, "training": item_training, "scene": item_scene,
         "dit-onnx": item_dit_onnx, "fun-camera-onnx": item_fun_camera_onnx, "camera-mini": item_camera_mini}


# --------------------------------------------------------------------------------------------------
# Parent: one subprocess per item
# --------------------------------------------------------------------------------------------------
def run_group(cmd: list[str], timeout: float) -> subprocess.CompletedProcess:
    """``subprocess.run`` in a new session whose whole process group is killed on timeout (an item's own
    subprocesses, e.g. explore's Prefect server, do not outlive it)."""
    import signal

    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired as exc:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        exc.output, exc.stderr = proc.communicate()  # what the item printed before its cap: its log keeps it
        raise
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def keep_item_log(name: str, ctx: dict, stdout: str | None, stderr: str | None) -> dict:
    """Write an item's printed output to ``items/<name>.log`` in the output folder (it comes back with the results)
    and return its last lines, so a timed-out or failed item says how far it got."""
    text = (stdout or "") + ("\n--- stderr ---\n" + stderr if stderr else "")
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith("{")]
    res: dict = {"log_tail": lines[-12:]} if lines else {}
    if ctx.get("out") and text.strip():
        log = Path(ctx["out"]) / "items" / f"{name}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        log.write_text(text)
        res["log"] = str(log)
    return res


def _partial(path: Path) -> dict:
    try:
        return {"partial": json.loads(path.read_text())} if path.is_file() else {}
    except ValueError:
        return {}


def run_item_subprocess(name: str, ctx: dict, cap: float) -> dict:
    partial = Path(ctx["work"]) / f"{name}.partial.json"
    partial.unlink(missing_ok=True)
    spec = json.dumps(dict(ctx, cap=cap, partial=str(partial)))
    t0 = time.perf_counter()
    try:
        p = run_group([sys.executable, __file__, "--item", name, "--spec", spec], cap)
    except subprocess.TimeoutExpired as exc:
        log = keep_item_log(name, ctx, exc.output, exc.stderr)
        last = (log.get("log_tail") or ["nothing printed"])[-1]
        return {"status": "timeout", "cap_s": cap, "wall_s": time.perf_counter() - t0,
                "reason": f"cut at its cap of {cap:.0f} s; its last line: {last}", **log, **_partial(partial)}
    log = keep_item_log(name, ctx, p.stdout, p.stderr)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    if p.returncode != 0 or not lines:
        return {"status": "error", "returncode": p.returncode, "error": (p.stderr or p.stdout)[-3000:],
                "wall_s": time.perf_counter() - t0, "cap_s": cap, **log, **_partial(partial)}
    out = json.loads(lines[-1])
    out.update({"wall_s": time.perf_counter() - t0, "cap_s": cap, **{k: v for k, v in log.items() if k == "log"}})
    return out


def item_error(exc: BaseException) -> dict:
    """An item's exception as its result. A failed import is reported as one, naming the missing module and what
    to do (never as a module that "does not exist yet")."""
    tb = traceback.format_exc()[-3000:]
    if isinstance(exc, ImportError):
        missing = getattr(exc, "name", None) or ""
        if missing.split(".")[0] == "navcrafter":
            hint = ("navcrafter is not importable here: run the check through deploy/gpu/run_check.sh (it makes the "
                    "tree importable without installing it) or install the project")
        elif missing:
            hint = f"the module {missing!r} is missing here: carry its wheel (deploy/gpu/wheels.txt)"
        else:
            hint = "an import failed inside a module: see the traceback"
        return {"status": "import error", "missing_module": missing or None, "error": f"{type(exc).__name__}: {exc}",
                "reason": f"failed import ({type(exc).__name__}: {exc}); {hint}", "traceback": tb}
    return {"status": "error", "error": f"{type(exc).__name__}: {exc}", "traceback": tb}


def child(name: str, spec: str) -> int:
    ctx = json.loads(spec)
    Path(ctx["work"]).mkdir(parents=True, exist_ok=True)
    try:
        res = FUNCS[name](ctx)
    except Exception as exc:  # the parent records it; the other items still run
        res = item_error(exc)
    if "status" not in res:  # an item that forgot its status is a bug in this file, never a silent blank
        res = {"status": "error", "error": f"item {name} returned no status", "result": res}
    print(json.dumps(res, default=str))
    return 0


def _compose(results: dict) -> dict:
    try:
        return compose_scene(results)
    except Exception as exc:  # recorded, never fatal: the measured items are already written
        return {"status": "error", "error": f"{type(exc).__name__}: {exc}"}


def run_all(ctx: dict, items: list[str], inline: bool = False, deadline: float | None = None,
            on_item=None, previous: dict | None = None) -> dict:
    """Each item in its own process under its cap (``--inline``: in this one, no caps). ``deadline`` (epoch s): an
    item's cap is cut to the time left, and an item with less than ``MIN_ITEM_S`` left is ``not run``.
    ``on_item(results)`` runs after every item (main rewrites results.json/results.md there)."""
    results = dict(previous or {})
    for name in items:
        cap = CAPS[name][1 if ctx["quick"] else 0] * (4 if ctx["dry_run"] else 1)
        if name == "scene" and ctx.get("with_explore"):
            cap = EXPLORE_CAP
        left = None if deadline is None else deadline - time.time()
        if left is not None and left < MIN_ITEM_S:
            results[name] = {"status": "not run", "cap_s": cap,
                             "reason": f"out of time: {max(left, 0):.0f} s left of the run's budget (--deadline); "
                                       f"rerun with --items {name} --keep"}
        else:
            if left is not None and left < cap:
                cap = int(left)
            print(f"gpu_check: {name} (cap {cap} s) ...", file=sys.stderr, flush=True)
            if inline:
                t0 = time.perf_counter()
                try:
                    r = FUNCS[name](dict(ctx, cap=cap))
                except Exception as exc:
                    r = item_error(exc)
                r["wall_s"] = time.perf_counter() - t0
            else:
                r = run_item_subprocess(name, ctx, cap)
            results[name] = r
        print(f"gpu_check: {name}: {results[name].get('status')} in {results[name].get('wall_s', 0):.1f} s",
              file=sys.stderr, flush=True)
        if results.get("scene", {}).get("status") == "ok":
            results["scene"]["composed"] = _compose(results)
        if on_item:
            on_item(results)
    return results


def _env() -> dict:
    """The node, as far as it can be read; never fatal (a missing torch or onnxruntime is recorded)."""
    env: dict = {"python": platform.python_version(), "machine": platform.machine(), "cpus": os.cpu_count()}
    try:
        import torch

        env.update(torch=torch.__version__, cuda=torch.version.cuda,
                   device=torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu")
    except Exception as exc:
        env.update(torch=None, device="unknown", torch_error=f"{type(exc).__name__}: {exc}")
    try:
        import onnxruntime

        env["onnxruntime"] = onnxruntime.__version__
        env["ort_providers"] = onnxruntime.get_available_providers()
    except Exception as exc:
        env["onnxruntime"] = None
        env["onnxruntime_error"] = f"{type(exc).__name__}: {exc}"
    return env


# --------------------------------------------------------------------------------------------------
# Preflight: what the node has, before any minute is spent on it
# --------------------------------------------------------------------------------------------------
# module -> (what needs it, required): a required one failing makes the preflight fail (most items would fail)
PREFLIGHT_MODULES: dict[str, tuple[str, bool]] = {
    "navcrafter.models": ("everything (the project's tree)", True),
    "pydantic": ("schemas.config: gsplat, training, scene", True),
    "diffusers": ("dit, fun-camera, difix, training (Wan / SD modules)", True),
    "transformers": ("moge, difix (DINOv2 / CLIP modules)", True),
    "navcrafter.schemas.config": ("gsplat, training, scene", True),
    "navcrafter.models.synthesis.camcontrol": ("dit, training", True),
    "navcrafter.models.geometry.vggt": ("vggt", True),
    "navcrafter.models.geometry.moge": ("moge", True),
    "navcrafter.models.refiner.difix": ("difix", True),
    "navcrafter.models.gaussians.train": ("gsplat", True),
    "navcrafter.models.synthesis.training": ("training", True),
    "navcrafter.models.synthesis.funcamera": ("fun-camera", False),
    "onnx": ("the opt-in *-onnx items", False),
    "onnxscript": ("the opt-in *-onnx items (dynamo export)", False),
    "navcrafter.models.runtime.onnxio": ("the opt-in *-onnx items", False),
    "gsplat": ("gsplat (its package only: importing it builds nothing)", False),
}
# the sibling benchmark scripts the items run (benchmarks/ is not a package)
PREFLIGHT_BENCH: dict[str, tuple[str, bool]] = {
    "synthesis": ("dit, the *-onnx items", True), "gsplat_fit": ("gsplat", True),
    "camera_training_gpu": ("training", True),
}


def _tool(cmd: list[str], line: int = -1) -> str | None:
    """``EXE: a line of its output`` (the last by default), or None when it is not on the PATH."""
    import shutil

    exe = shutil.which(cmd[0])
    if exe is None:
        return None
    try:
        p = subprocess.run([exe, *cmd[1:]], capture_output=True, text=True, timeout=30)
        lines = (p.stdout or p.stderr).strip().splitlines()
        return f"{exe}: {lines[line] if lines else ''}".strip()
    except (OSError, subprocess.SubprocessError) as exc:
        return f"{exe}: {type(exc).__name__}: {exc}"


def preflight(device: str = "cuda") -> dict:
    """Imports, CUDA, onnxruntime's execution providers, nvcc / the C++ compiler / ninja, whether gsplat is built.
    ``ok`` is False when the check cannot usefully run (no torch, no CUDA device, navcrafter or a module most items
    need does not import); the rest are reported as limits (what will be skipped, and why)."""
    import importlib

    checks: list[dict] = []

    def add(name, ok, detail, required):
        checks.append({"check": name, "ok": bool(ok), "required": required, "detail": detail})

    add("python", True, f"{platform.python_version()} ({sys.executable})", False)
    try:
        import torch

        add("torch", True, f"{torch.__version__} (CUDA build: {torch.version.cuda or 'no'})", True)
        cuda = torch.cuda.is_available()
        if cuda:
            props = torch.cuda.get_device_properties(0)
            detail = (f"{props.name}, compute capability {props.major}.{props.minor}, "
                      f"{props.total_memory / 2**30:.0f} GiB, {torch.cuda.device_count()} device(s)")
        else:
            detail = "torch sees no CUDA device" + (" (fine for the CPU dry run)" if device == "cpu" else "")
        add("cuda device", cuda, detail, device == "cuda")
    except Exception as exc:
        add("torch", False, f"{type(exc).__name__}: {exc}", True)
    for mod, (needed_by, required) in PREFLIGHT_MODULES.items():
        try:
            m = importlib.import_module(mod)
            detail = f"{getattr(m, '__version__', '')} {Path(getattr(m, '__file__', '') or '').parent}".strip()
            add(f"import {mod}", True, detail, required)
        except Exception as exc:
            add(f"import {mod}", False, f"{item_error(exc).get('reason') or exc} (needed by: {needed_by})", required)
    for mod, (needed_by, required) in PREFLIGHT_BENCH.items():
        try:
            _bench_import(mod)
            add(f"import benchmarks/{mod}.py", True, "", required)
        except Exception as exc:
            add(f"import benchmarks/{mod}.py", False, f"{item_error(exc).get('reason') or exc} (needed by: "
                f"{needed_by})", required)
    try:
        import onnxruntime

        providers = onnxruntime.get_available_providers()
        add("onnxruntime CUDA execution provider", "CUDAExecutionProvider" in providers,
            f"onnxruntime {onnxruntime.__version__}: {providers}" + (
                "" if "CUDAExecutionProvider" in providers else
                "; a CPU build: the ONNX-on-GPU halves of the DiT items cannot run here (onnxruntime-gpu, ~256 MB, "
                "cannot travel)"), False)
    except Exception as exc:
        add("onnxruntime", False, f"{type(exc).__name__}: {exc}", False)
    try:
        from torch.utils.cpp_extension import _find_cuda_home

        home = _find_cuda_home()
    except Exception:
        home = None
    nvcc = _tool([str(Path(home) / "bin" / "nvcc") if home else "nvcc", "--version"])
    add("nvcc", nvcc is not None, f"{nvcc} (CUDA_HOME {home})" if nvcc else "no CUDA compiler: gsplat cannot be "
        "built", False)
    cxx = _tool(["c++", "--version"], 0) or _tool(["g++", "--version"], 0)
    add("c++ compiler", cxx is not None, (cxx or "none on the PATH").splitlines()[0], False)
    ninja = _tool(["ninja", "--version"])
    add("ninja", ninja is not None, ninja or "not on the PATH (torch's JIT builds need it)", False)
    st = gsplat_state()
    add("gsplat built", st.get("built", False), st.get("library") if st.get("built") else st.get("reason"), False)
    failed = [c for c in checks if c["required"] and not c["ok"]]
    return {"ok": not failed, "device": device, "checks": checks, "gsplat": st,
            "fatal": [f"{c['check']}: {c['detail']}" for c in failed]}


def preflight_text(pf: dict) -> str:
    lines = [f"{'ok ' if c['ok'] else ('FAIL' if c['required'] else 'no  ')} {c['check']}: {c['detail']}"
             for c in pf["checks"]]
    lines.append("preflight: " + ("ok" if pf["ok"] else "FAILED: " + "; ".join(pf["fatal"])))
    return "\n".join(lines)


def _s(x) -> str:
    return "—" if x is None else (f"{x:.3f} s" if x < 10 else f"{x:.1f} s")


def _gib(x) -> str:
    return "—" if x is None else f"{x:.1f} GiB"


def _dit_row(d: dict) -> tuple[str, str]:
    ort = d.get("ort", {})
    text = f"torch {d['torch_dtype']} {_s(d['torch']['median_s'])}"
    if "export_s" in d:
        text += f"; ONNX export {d['export_s']:.0f} s"
        if "convert_fp16_s" in d:
            text += f", fp16 conversion {d['convert_fp16_s']:.0f} s"
    mem = f"torch {_gib(d['torch'].get('peak_gib'))}"
    if "median_s" in ort:
        text += (f" vs onnxruntime {d['onnx_dtype']} {_s(ort['median_s'])} (×{d['ort_over_torch']:.2f}); "
                 f"max rel. diff {d['ort_vs_torch_max_rel_diff']:.1e}")
        mem += f", ORT {_gib(ort.get('peak_gib'))}"
    elif ort:
        text += f"; onnxruntime {ort.get('status')}: {ort.get('reason')}"
    return text, mem


def limits(report: dict) -> list[str]:
    """What could not run on this node, and why (results.md says it; results.json holds it as ``limits``)."""
    r, env, out = report["items"], report["env"], []
    providers = env.get("ort_providers") or []
    if report.get("device") == "cuda" and "CUDAExecutionProvider" not in providers:
        out.append(f"onnxruntime {env.get('onnxruntime')} has no CUDA execution provider here ({providers}): the "
                   "ONNX-on-GPU half of the DiT items cannot run (onnxruntime-gpu, ~256 MB, cannot travel in 64 "
                   "MiB); `dit` / `fun-camera` time torch only, the opt-in `dit-onnx` / `fun-camera-onnx` export and "
                   "convert the graph and do not run it")
    for name, it in r.items():
        status = it.get("status")
        if status in ("ok",):
            continue
        why = it.get("reason") or (it.get("error") or "").strip().splitlines()[-1:] or ["?"]
        why = why if isinstance(why, str) else why[0]
        out.append(f"`{name}`: {status}: {why}")
    not_asked = [n for n in OPT_IN if n not in r]
    if not_asked:
        out.append(f"opt-in items not asked for: {', '.join(not_asked)} (add them to --items; own caps "
                   f"{', '.join(f'{n} {OPT_IN[n][0]} s' for n in not_asked)})")
    return out


def markdown(report: dict) -> str:
    r, env = report["items"], report["env"]
    lines = [f"# GPU check{' — quick' if report['quick'] else ''}", ""]
    if report["dry_run"]:
        lines += [f"**{DRY_RUN_LABEL}.**", ""]
    if report.get("running"):
        lines += [f"**Incomplete: written after item {len(r)} of {len(report.get('asked', r))}; the run was still "
                  "going (a cut run keeps what it measured).**", ""]
    lines += [f"{env.get('device')}; torch {env.get('torch')} (CUDA {env.get('cuda')}), onnxruntime "
              f"{env.get('onnxruntime')}; Python {env.get('python')}; random weights everywhere; "
              f"{report['wall_s']:.0f} s in all.", "",
              "| item | status | result | peak memory | wall (cap) |", "|---|---|---|---|---|"]

    def row(name, result, mem):
        if name not in r:
            return
        it = r[name]
        status = it.get("status", "—")
        if status != "ok":
            result = it.get("reason") or (it.get("error") or "").strip().splitlines()[-1:] or [""]
            result = result if isinstance(result, str) else result[0]
            result = result.replace("|", "/")[:240]
            if "torch" in it.get("partial", {}):
                result = (f"torch {it['partial'].get('torch_dtype')} {_s(it['partial']['torch']['median_s'])} "
                          f"(then stopped: {status}) " + result).strip()
                mem = f"torch {_gib(it['partial']['torch'].get('peak_gib'))}"
        lines.append(f"| {name} | {status} | {result} | {mem} | {it.get('wall_s', 0):.0f} s "
                     f"({it.get('cap_s', '—')} s) |")

    g = r.get("gsplat", {})
    gf = g.get("gsplat_fit") or {}
    row("gsplat", f"{gf.get('its_per_s', 0):.1f} it/s ({g.get('gaussians', 0):,} Gaussians, {g.get('size')}²); "
        f"first call {g.get('first_call_seconds', 0):.1f} s; parity CPU vs gsplat colour max "
        f"{(g.get('parity_small_cpu_vs_gsplat') or {}).get('colour', {}).get('max', float('nan')):.1e}",
        _gib(gf.get("peak_mem_gib")))
    for name in ("dit", "fun-camera"):
        d = r.get(name, {})
        row(name, *(_dit_row(d) if d.get("status") == "ok" else ("", "—")))
    v = r.get("vggt", {})
    row("vggt", f"{_s(v.get('median_s'))} for {v.get('frames')} frames at {v.get('size')}²", _gib(v.get("peak_gib")))
    m = r.get("moge", {})
    row("moge", f"{_s(m.get('median_s'))} at {m.get('size')} ({m.get('tokens')} tokens)", _gib(m.get("peak_gib")))
    d = r.get("difix", {})
    row("difix", f"{_s(d.get('median_s'))} at {d.get('size')}² ({d.get('dtype')}, reference view)",
        _gib(d.get("peak_gib")))
    t = r.get("training", {})
    row("training", f"train step {_s(t.get('train_step_s'))}, sampling step (CFG pair) "
        f"{_s(t.get('sample_step_cfg_pair_s'))}", f"{_gib(t.get('train_peak_gib'))} / {_gib(t.get('sample_peak_gib'))}")
    for name in ("dit-onnx", "fun-camera-onnx"):
        d = r.get(name, {})
        row(name, *(_dit_row(d) if d.get("status") == "ok" else ("", "—")))
    cm = r.get("camera-mini", {})
    if cm.get("status") == "ok":
        tr, un, wr, st = cm["trained"], cm["untrained"], cm["trained_wrong_cameras"], cm["setup"]
        tm = st.get("timings_s", {})
        row("camera-mini", f"direction accuracy {tr['direction_accuracy']:.3f} (untrained "
            f"{un['direction_accuracy']:.3f}, mirrored cameras {wr['direction_accuracy']:.3f}); R_err "
            f"{tr['r_err']:.2f}°/frame (floor {cm['floor']['r_err']:.2f}); gap {tr['camera_gap']:+.4f} ± "
            f"{tr['camera_gap_se']:.4f}; {st.get('base_steps')} + {st.get('control_steps')} steps: base "
            f"{tm.get('base_s', 0):.0f} s, control {tm.get('control_s', 0):.0f} s, sampling "
            f"{tm.get('sampling_s', 0):.0f} s (SIMULATION; trained from scratch)", "—")
    else:  # cut short or failed: the stages it finished (``--progress``)
        pr = cm.get("partial") or {}
        done = [f"{k} direction {pr[k]['direction_accuracy']:.3f}, R_err {pr[k]['r_err']:.2f}°"
                for k in ("trained", "untrained", "trained_wrong_cameras") if k in pr]
        if "base_final_loss" in pr:
            done.insert(0, f"trained: final loss base {pr['base_final_loss']:.4f}, control "
                           f"{pr['control_final_loss']:.4f}")
        row("camera-mini", ("finished before it stopped: " + "; ".join(done)) if done else "", "—")
    sc = r.get("scene", {})
    comp, ex = sc.get("composed") or {}, sc.get("explore") or {}
    summary = ""
    if comp.get("status") == "error":
        summary = f"composition failed: {comp['error']}"
    elif comp:
        summary = (f"learned models composed: {comp['total_min']:.2f} min/scene vs the paper's {PAPER_SCENE_MIN} "
                   f"(×{comp['over_paper']:.2f}; DiT at {comp.get('dit_width')} width"
                   + (f"; missing {', '.join(comp['missing'])}" if comp["missing"] else "") + ")")
    if ex.get("status") == "ok":
        summary += f"; explore flow (tiny models) {ex['explore_min']:.2f} min"
    elif ex:
        summary += f"; explore flow: {ex.get('status')}"
    row("scene", summary, "—")
    lim = report.get("limits") or []
    if lim:
        lines += ["", "## What did not run here, and why", ""] + [f"- {x}" for x in lim]
    lines += ["", "Notes: DiT = one call on the classifier-free-guidance pair (batch 2), 81 frames at 256² "
              "(21 × 16 × 16 latent tokens per sample), torch bf16; the opt-in `*-onnx` items export the same module "
              "to ONNX and, where onnxruntime has a CUDA execution provider, run the fp16 graph `models convert-fp16` "
              "makes of it (fp32 norms), whose output differs from bf16 torch by rounding. The composed scene time "
              "is a lower bound (N × steps × DiT step + VGGT per lift + MoGe + fit iterations / it/s; no VAE, no "
              "CLIP) at the 1.3B width, not the 14B base's. Random weights: no number here says anything about "
              "quality.", ""]
    return "\n".join(lines)


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path)
    ap.add_argument("--quick", action="store_true", help="smaller sizes and caps (~5 min at most)")
    ap.add_argument("--items", default=",".join(ITEMS), help=f"comma-separated subset of {', '.join(ITEMS)}, "
                    f"and the opt-in {', '.join(OPT_IN)}")
    ap.add_argument("--device", default="cuda", choices=("cuda", "cpu"))
    ap.add_argument("--dry-run", action="store_true", help="with --device cpu: tiny configs, plumbing only (tests); "
                                                            "NOT a measurement")
    ap.add_argument("--inline", action="store_true", help="run the items in this process (no caps; tests)")
    ap.add_argument("--work", type=Path, help="scratch folder: partial results, ONNX files, scene models (default "
                                              "OUT/work; run_check.sh keeps it out of $OUT)")
    ap.add_argument("--deadline", type=float, help="epoch seconds by which the run must have written its results: "
                    "caps are cut to the time left, items past it are `not run` (run_check.sh sets it)")
    ap.add_argument("--keep", action="store_true", help="keep the items of an earlier results.json in --out (a rerun "
                                                        "of some items)")
    ap.add_argument("--preflight", action="store_true", help="only check the node (imports, CUDA, onnxruntime's "
                    "providers, nvcc / compiler / ninja, gsplat built) and exit: 0 ok, 3 with the reasons")
    ap.add_argument("--build-gsplat", action="store_true", help="only build gsplat's CUDA kernels (its JIT build, "
                    "resumable; run it under a time cap) and exit: 0 built, 4 not")
    ap.add_argument("--with-explore", action="store_true", help="also time the whole explore flow (backend onnx, "
                    f"tiny random-weight models at the paper's clip size; cap {EXPLORE_CAP} s, beyond the budget)")
    ap.add_argument("--scene-models", type=Path, help="prepared models for --with-explore (default WORK/"
                                                      "scene-models)")
    ap.add_argument("--prepare-scene-models", action="store_true", help="only export those models (CPU is enough; "
                                                                        "many minutes), then exit")
    ap.add_argument("--prepare-camera-scenes", action="store_true", help="only render the camera-mini item's "
                    f"scenes (a machine with open3d; with --dry-run the tiny ones) into {CAMERA_SCENES}, then exit")
    ap.add_argument("--camera-scenes", type=Path, help="the camera-mini item's scenes file (default: "
                    "deploy/gpu/scenes/camera-mini.pkl)")
    ap.add_argument("--item", help=argparse.SUPPRESS)
    ap.add_argument("--spec", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.item:
        return child(args.item, args.spec)
    if args.preflight:
        pf = preflight("cpu" if args.dry_run else args.device)
        print(preflight_text(pf), file=sys.stderr)
        if args.out:
            args.out.mkdir(parents=True, exist_ok=True)
            _write_atomic(args.out / "preflight.json", json.dumps(pf, indent=1, default=str))
        return 0 if pf["ok"] else 3
    if args.build_gsplat:
        res = build_gsplat()
        print(json.dumps(res, default=str))
        if args.out:
            args.out.mkdir(parents=True, exist_ok=True)
            _write_atomic(args.out / "gsplat-build.json", json.dumps(res, indent=1, default=str))
        return 0 if res.get("built") else 4
    if args.prepare_camera_scenes:
        print(json.dumps(prepare_camera_scenes(args.dry_run, args.camera_scenes)))
        return 0
    if args.out is None:
        ap.error("--out DIR is required")
    items = [i.strip() for i in args.items.split(",") if i.strip()]
    if bad := [i for i in items if i not in CAPS]:
        ap.error(f"unknown item(s) {bad}; choose from {list(ITEMS)} or the opt-in {list(OPT_IN)}")
    work = args.work or args.out / "work"
    if args.prepare_scene_models:
        models = args.scene_models or work / "scene-models"
        print(json.dumps(prepare_scene_models(models)))
        print(f"gpu_check: scene models ready in {models}", file=sys.stderr)
        return 0
    if args.device == "cpu" and not args.dry_run:
        ap.error("--device cpu is only for --dry-run (plumbing tests); the check itself needs CUDA")
    import torch

    if args.device == "cuda" and not torch.cuda.is_available():
        print(f"gpu_check: refusing to run: this check needs a CUDA GPU, and torch {torch.__version__} "
              f"(CUDA build: {torch.version.cuda or 'no'}) sees none. Run it on a machine with one GPU; "
              f"`--device cpu --dry-run` only exercises the plumbing.", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    ctx = {"device": args.device, "dry_run": args.dry_run, "quick": args.quick, "work": str(work),
           "with_explore": args.with_explore, "scene_models": str(args.scene_models) if args.scene_models else None,
           "out": str(args.out), "camera_scenes": str(args.camera_scenes) if args.camera_scenes else None}
    os.makedirs(ctx["work"], exist_ok=True)
    previous = {}
    if args.keep and (args.out / "results.json").is_file():
        try:
            previous = json.loads((args.out / "results.json").read_text()).get("items", {})
        except ValueError:
            previous = {}
    env, t0 = _env(), time.perf_counter()
    base = {"label": DRY_RUN_LABEL if args.dry_run else "measurement (random weights)", "dry_run": args.dry_run,
            "quick": args.quick, "device": args.device, "env": env, "asked": items,
            "paper_min_per_scene": PAPER_SCENE_MIN}

    def write(results: dict, running: bool = True) -> dict:
        report = base | {"items": results, "wall_s": time.perf_counter() - t0, "running": running}
        report["limits"] = limits(report)
        _write_atomic(args.out / "results.json", json.dumps(report, indent=1, default=str))
        _write_atomic(args.out / "results.md", markdown(report))
        return report

    write(previous)
    results = run_all(ctx, items, inline=args.inline, deadline=args.deadline, on_item=write, previous=previous)
    report = write(results, running=False)
    print(markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
