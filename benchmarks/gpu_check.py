"""The prepared GPU check: every CUDA measurement the project still owes, as one command on one GPU in < 8 minutes.

    python benchmarks/gpu_check.py --out bench-out/gpu-check            # ~7 min at most (per-item time caps)
    python benchmarks/gpu_check.py --out bench-out/gpu-check --quick    # ~5 min at most, smaller sizes
    python benchmarks/gpu_check.py --out bench-out/gpu-check --prepare-scene-models   # once, any machine
    python benchmarks/gpu_check.py --out bench-out/gpu-check --with-explore           # + the whole flow

Random weights everywhere (timing, memory and precision only; no quality). Items, each in its own subprocess with
its own time cap (a failure, a crash or a timeout of one is recorded and the next one runs):

* ``gsplat``: ``benchmarks/gsplat_fit.py``'s ``run`` (its quick size): iterations/s of the gsplat-backed fit,
  first-call kernel build, parity of our renderer vs gsplat; skipped with its reason without gsplat.
* ``dit``: one denoising step (CFG pair) of the camera-controlled Wan DiT at Wan2.1-1.3B width, 81 frames at
  256² (``benchmarks/synthesis.py``'s ``build``/``make_inputs``): torch bf16 vs onnxruntime CUDA EP on the
  product's fp16 graph of the same module (fp32 ``onnxio.export_graph``, then ``onnxio.convert_graph_fp16`` as
  ``navcrafter models convert-fp16`` does: fp32 normalisations and IO), step times, peak memory
  (``torch.cuda.max_memory_allocated``;
  onnxruntime: NVML process memory, which includes the process's CUDA context), and the fp16-ORT vs bf16-torch
  output difference. Without onnxruntime's CUDA execution provider (``onnxruntime-gpu``) only torch is timed.
* ``fun-camera``: the Fun-Camera DiT (``navcrafter.models.synthesis.funcamera``, 1.3B config, same latent grid)
  the same way, when that module imports with what this needs; otherwise a ``not built`` entry naming why.
* ``vggt``: VGGT-1B (``models/geometry/vggt.py``, full config) on 25 frames at 518², bf16 autocast.
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
  ``OUT/work/scene-models``). That explore path was checked once on the CPU (2 shared cores, onnxruntime CPU, fit on
  the CPU): the room demo scene finished in 4.3 min (plumbing only, not a GPU number).

Writes ``results.json`` (every item's status, numbers, errors) and ``results.md``. Refuses without CUDA (exit code
2). ``--device cpu --dry-run`` runs the plumbing with tiny configs on the CPU for the tests: its numbers are NOT
measurements and every output says so.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
PAPER_SCENE_MIN = 4.79  # NavCrafter, Table V: minutes per scene
DRY_RUN_LABEL = "DRY RUN (CPU, tiny configs): plumbing only, NOT a measurement"
EXPLORE_CAP = 600  # --with-explore: the scene item's cap (beyond the 8-minute budget)

# name -> (full cap s, quick cap s): the full caps sum to 415 s (~7 min), the quick ones to 305 s. The two DiT items
# include exporting a 1.3B-parameter module to ONNX (dynamo + onnxscript's optimiser), the bulk of their time; what
# an item measured before its cap is kept ("partial").
ITEMS: dict[str, tuple[int, int]] = {
    "gsplat": (50, 40), "dit": (140, 100), "fun-camera": (80, 60), "vggt": (30, 20), "moge": (20, 15),
    "difix": (20, 15), "training": (60, 40), "scene": (15, 15),
}


def _bench_import(name: str):
    """A sibling benchmark module (benchmarks/ is not a package)."""
    import importlib

    if str(HERE) not in sys.path:
        sys.path.insert(0, str(HERE))
    return importlib.import_module(name)


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
def item_gsplat(ctx: dict) -> dict:
    g = _bench_import("gsplat_fit")
    why = g.refuse_without_cuda()
    if why:
        return {"status": "skipped", "reason": why}
    ns = argparse.Namespace(quick=True, gaussians=100_000 if not ctx["quick"] else 50_000, size=128, views=8,
                            iterations=100 if not ctx["quick"] else 60, torch_iterations=3, densify=False)
    r = g.run(ns)
    r["markdown"] = g.markdown(r)
    return r


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
    (bf16 on CUDA, fp32 in a dry run) timing, then an ONNX export of the same weights on ORT: on CUDA the product's
    fp16 path (an fp32 export converted by ``onnxio.convert_graph_fp16``, as ``navcrafter models convert-fp16`` does:
    fp16 with fp32 normalisations and inputs/outputs), in a dry run the fp32 export."""
    import torch

    from navcrafter.models.runtime.onnxio import convert_graph_fp16, export_graph

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
    if device == "cuda":
        import onnxruntime

        if "CUDAExecutionProvider" not in onnxruntime.get_available_providers():
            res["status"] = "ok"
            res["ort"] = {"status": "skipped", "reason": f"onnxruntime {onnxruntime.__version__} has no CUDA "
                          "execution provider here (install onnxruntime-gpu matching the CUDA version)"}
            return res
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
    import importlib.util

    name = "navcrafter.models.synthesis.funcamera"
    try:
        found = importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        found = False
    if not found:
        return {"status": "not built", "reason": f"{name} does not exist yet (being built); rerun when it does"}
    import importlib

    try:
        mod = importlib.import_module(name)
    except Exception as exc:  # a half-built module: record why
        return {"status": "not built", "reason": f"{name} does not import: {type(exc).__name__}: {exc}"}
    needed = ("FunCameraConfig", "build_fun_camera", "fun_example_inputs", "_FunExportWrapper", "FUN_DIT_INPUTS",
              "FUN_DIT_OUTPUTS")
    if lacking := [n for n in needed if not hasattr(mod, n)]:
        return {"status": "not built", "reason": f"{name} imports but lacks {', '.join(lacking)}"}
    config = mod.FunCameraConfig.tiny() if ctx["dry_run"] else mod.FunCameraConfig.wan_1_3b()
    # latent grid of 81 frames at 256² (dry run: 5 frames at 32²... in tiny latents), batch 2 (the CFG pair)
    shape = (2, 2, 4, 4) if ctx["dry_run"] else (2, 21, 32, 32)
    dev = "cpu" if ctx["dry_run"] else ctx["device"]
    box = [mod.build_fun_camera(config, device=dev)]
    inputs = {k: v.float() for k, v in mod.fun_example_inputs(box[0], shape).items()}
    names = list(mod.FUN_DIT_INPUTS)
    return _torch_vs_ort(lambda: mod._FunExportWrapper(box.pop()), inputs, names, list(mod.FUN_DIT_OUTPUTS), ctx,
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
    from navcrafter.flows.cli.options import run_config

    s = run_config("paper").synthesis
    out = {}
    roles = {"synthesizer": ["export-synthesizer", "--frames", str(s.num_frames), "--height", str(s.height),
                             "--width", str(s.width)],
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


def item_scene(ctx: dict) -> dict:
    res: dict = {"status": "ok", "paper_min_per_scene": PAPER_SCENE_MIN}
    if ctx["dry_run"]:
        res["explore"] = {"status": "not run in a dry run"}
        return res
    if not ctx.get("with_explore"):
        res["explore"] = {"status": "not run", "reason": "pass --with-explore (after --prepare-scene-models) to "
                                                         "time the whole flow as well (beyond the 8-minute budget)"}
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
    CLIP image encoding and data movement are not measured here)."""
    from navcrafter.flows.cli.options import run_config

    cfg = run_config("paper")
    n, steps, frames = cfg.iterations, cfg.synthesis.steps, cfg.lift.max_views + 1
    terms, missing = {}, []
    dit = results.get("dit", {})
    dit = dit if dit.get("status") == "ok" else dit.get("partial", {})  # torch timed before an ORT failure
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
        terms["fit"] = cfg.fit.iterations / gs["gsplat_fit"]["its_per_s"]
    else:
        missing.append("fit (gsplat)")
    total = sum(terms.values())
    return {"iterations": n, "steps": steps, "geometry_frames_per_lift": frames, "terms_s": terms,
            "total_s": total, "total_min": total / 60, "over_paper": (total / 60) / PAPER_SCENE_MIN,
            "missing": missing, "dit_width": dit.get("config")}


FUNCS = {"gsplat": item_gsplat, "dit": item_dit, "fun-camera": item_fun_camera, "vggt": item_vggt,
         "moge": item_moge, "difix": item_difix, "training": item_training, "scene": item_scene}


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
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.communicate()
        raise
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


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
    except subprocess.TimeoutExpired:
        return {"status": "timeout", "cap_s": cap, "wall_s": time.perf_counter() - t0, **_partial(partial)}
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    if p.returncode != 0 or not lines:
        return {"status": "error", "returncode": p.returncode, "error": (p.stderr or p.stdout)[-3000:],
                "wall_s": time.perf_counter() - t0, "cap_s": cap, **_partial(partial)}
    out = json.loads(lines[-1])
    out.update({"wall_s": time.perf_counter() - t0, "cap_s": cap})
    return out


def child(name: str, spec: str) -> int:
    ctx = json.loads(spec)
    Path(ctx["work"]).mkdir(parents=True, exist_ok=True)
    try:
        res = FUNCS[name](ctx)
    except Exception as exc:  # the parent records it; the other items still run
        res = {"status": "error", "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()[-3000:]}
    print(json.dumps(res, default=str))
    return 0


def run_all(ctx: dict, items: list[str], inline: bool = False) -> dict:
    results = {}
    for name in items:
        cap = ITEMS[name][1 if ctx["quick"] else 0] * (4 if ctx["dry_run"] else 1)
        if name == "scene" and ctx.get("with_explore"):
            cap = EXPLORE_CAP
        print(f"gpu_check: {name} (cap {cap} s) ...", file=sys.stderr, flush=True)
        if inline:
            t0 = time.perf_counter()
            try:
                r = FUNCS[name](dict(ctx, cap=cap))
            except Exception as exc:
                r = {"status": "error", "error": f"{type(exc).__name__}: {exc}"}
            r["wall_s"] = time.perf_counter() - t0
        else:
            r = run_item_subprocess(name, ctx, cap)
        results[name] = r
        print(f"gpu_check: {name}: {r.get('status')} in {r.get('wall_s', 0):.1f} s", file=sys.stderr, flush=True)
    if "scene" in results and results["scene"].get("status") == "ok":
        results["scene"]["composed"] = compose_scene(results)
    return results


def _env() -> dict:
    import torch

    env = {"python": platform.python_version(), "torch": torch.__version__, "cuda": torch.version.cuda,
           "machine": platform.machine()}
    try:
        import onnxruntime

        env["onnxruntime"] = onnxruntime.__version__
        env["ort_providers"] = onnxruntime.get_available_providers()
    except ImportError:
        env["onnxruntime"] = None
    env["device"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"
    return env


def _s(x) -> str:
    return "—" if x is None else (f"{x:.3f} s" if x < 10 else f"{x:.1f} s")


def _gib(x) -> str:
    return "—" if x is None else f"{x:.1f} GiB"


def markdown(report: dict) -> str:
    r, env = report["items"], report["env"]
    lines = [f"# GPU check{' — quick' if report['quick'] else ''}", ""]
    if report["dry_run"]:
        lines += [f"**{DRY_RUN_LABEL}.**", ""]
    lines += [f"{env['device']}; torch {env['torch']} (CUDA {env['cuda']}), onnxruntime {env.get('onnxruntime')}; "
              f"random weights everywhere; {report['wall_s']:.0f} s in all.", "",
              "| item | status | result | peak memory | wall (cap) |", "|---|---|---|---|---|"]

    def row(name, result, mem):
        if name not in r:
            return
        it = r[name]
        status = it.get("status", "—")
        if status != "ok":
            result = it.get("reason") or (it.get("error") or "").strip().splitlines()[-1:] or [""]
            result = result if isinstance(result, str) else result[0]
            result = result.replace("|", "/")[:160]
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
        if d.get("status") == "ok" and d.get("ort", {}).get("status") == "skipped":
            row(name, f"torch {d['torch_dtype']} {_s(d['torch']['median_s'])}; onnxruntime: {d['ort']['reason']}",
                f"torch {_gib(d['torch'].get('peak_gib'))}")
        elif d.get("status") == "ok":
            row(name, f"torch {d['torch_dtype']} {_s(d['torch']['median_s'])} vs onnxruntime {d['onnx_dtype']} "
                f"{_s(d['ort']['median_s'])} (×{d['ort_over_torch']:.2f}; export {d['export_s']:.0f} s); "
                f"max rel. diff {d['ort_vs_torch_max_rel_diff']:.1e}",
                f"torch {_gib(d['torch'].get('peak_gib'))}, ORT {_gib(d['ort'].get('peak_gib'))}")
        else:
            row(name, "", "—")
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
    sc = r.get("scene", {})
    comp, ex = sc.get("composed") or {}, sc.get("explore") or {}
    summary = ""
    if comp:
        summary = (f"learned models composed: {comp['total_min']:.2f} min/scene vs the paper's {PAPER_SCENE_MIN} "
                   f"(×{comp['over_paper']:.2f}; DiT at {comp.get('dit_width')} width"
                   + (f"; missing {', '.join(comp['missing'])}" if comp["missing"] else "") + ")")
    if ex.get("status") == "ok":
        summary += f"; explore flow (tiny models) {ex['explore_min']:.2f} min"
    elif ex:
        summary += f"; explore flow: {ex.get('status')}"
    row("scene", summary, "—")
    lines += ["", "Notes: DiT = one call on the classifier-free-guidance pair (batch 2), 81 frames at 256² "
              "(21 × 16 × 16 latent tokens per sample); onnxruntime runs the fp16 graph `models convert-fp16` makes "
              "of the same module (fp32 norms) on the CUDA execution provider, so its output differs from bf16 torch "
              "by rounding. The composed scene time is "
              "a lower bound (N × steps × DiT step + VGGT per lift + MoGe + fit iterations / it/s; no VAE, no CLIP) at "
              "the 1.3B width, not the 14B base's. Random weights: no number here says anything about quality.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path)
    ap.add_argument("--quick", action="store_true", help="smaller sizes and caps (~5 min at most)")
    ap.add_argument("--items", default=",".join(ITEMS), help=f"comma-separated subset of {', '.join(ITEMS)}")
    ap.add_argument("--device", default="cuda", choices=("cuda", "cpu"))
    ap.add_argument("--dry-run", action="store_true", help="with --device cpu: tiny configs, plumbing only (tests); "
                                                            "NOT a measurement")
    ap.add_argument("--inline", action="store_true", help="run the items in this process (no caps; tests)")
    ap.add_argument("--with-explore", action="store_true", help="also time the whole explore flow (backend onnx, "
                    f"tiny random-weight models at the paper's clip size; cap {EXPLORE_CAP} s, beyond the budget)")
    ap.add_argument("--scene-models", type=Path, help="prepared models for --with-explore (default OUT/work/"
                                                      "scene-models)")
    ap.add_argument("--prepare-scene-models", action="store_true", help="only export those models (CPU is enough; "
                                                                        "many minutes), then exit")
    ap.add_argument("--item", help=argparse.SUPPRESS)
    ap.add_argument("--spec", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.item:
        return child(args.item, args.spec)
    if args.out is None:
        ap.error("--out DIR is required")
    items = [i.strip() for i in args.items.split(",") if i.strip()]
    if bad := [i for i in items if i not in ITEMS]:
        ap.error(f"unknown item(s) {bad}; choose from {list(ITEMS)}")
    if args.prepare_scene_models:
        models = args.scene_models or args.out / "work" / "scene-models"
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
    ctx = {"device": args.device, "dry_run": args.dry_run, "quick": args.quick, "work": str(args.out / "work"),
           "with_explore": args.with_explore, "scene_models": str(args.scene_models) if args.scene_models else None}
    os.makedirs(ctx["work"], exist_ok=True)
    t0 = time.perf_counter()
    results = run_all(ctx, items, inline=args.inline)
    report = {"label": DRY_RUN_LABEL if args.dry_run else "measurement (random weights)", "dry_run": args.dry_run,
              "quick": args.quick, "env": _env(), "items": results, "wall_s": time.perf_counter() - t0,
              "paper_min_per_scene": PAPER_SCENE_MIN}
    (args.out / "results.json").write_text(json.dumps(report, indent=1, default=str))
    md = markdown(report)
    (args.out / "results.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
