"""benchmarks/gpu_check.py without a GPU: the refusal, and the plumbing in its CPU dry run (tiny configs; its
numbers are not measurements)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest


@pytest.fixture(scope="module")
def gpu_check():
    from benchmarks import gpu_check

    return gpu_check


def test_refuses_without_cuda(gpu_check, tmp_path, monkeypatch, capsys):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert gpu_check.main(["--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "refusing to run" in err and "needs a CUDA GPU" in err
    assert not (tmp_path / "out" / "results.json").exists()
    with pytest.raises(SystemExit) as exc:  # the CPU only for the labelled dry run
        gpu_check.main(["--out", str(tmp_path / "out"), "--device", "cpu"])
    assert exc.value.code == 2


def test_item_caps_fit_the_budget(gpu_check):
    assert sum(full for full, _ in gpu_check.ITEMS.values()) <= 8 * 60 - 30
    assert sum(quick for _, quick in gpu_check.ITEMS.values()) <= 6 * 60
    assert set(gpu_check.ITEMS) | set(gpu_check.OPT_IN) == set(gpu_check.FUNCS)
    assert not set(gpu_check.ITEMS) & set(gpu_check.OPT_IN)


def test_dry_run_plumbing(gpu_check, tmp_path):
    out = tmp_path / "out"
    items = "gsplat,vggt,moge,training,scene"
    assert gpu_check.main(["--out", str(out), "--device", "cpu", "--dry-run", "--inline", "--items", items]) == 0
    report = json.loads((out / "results.json").read_text())
    assert report["dry_run"] and report["label"] == gpu_check.DRY_RUN_LABEL
    r = report["items"]
    assert list(r) == items.split(",")
    assert r["gsplat"]["status"] == "skipped" and "CUDA" in r["gsplat"]["reason"]
    assert r["training"]["status"] == "skipped"
    assert r["vggt"]["status"] == "ok" and r["vggt"]["frames"] == 2 and r["vggt"]["median_s"] > 0
    assert r["moge"]["status"] == "ok"
    comp = r["scene"]["composed"]
    assert comp["iterations"] == 3 and comp["steps"] == 40 and set(comp["terms_s"]) == {"vggt", "moge"}
    assert "dit" in comp["missing"]
    md = (out / "results.md").read_text()
    assert gpu_check.DRY_RUN_LABEL in md and "| vggt | ok |" in md and "| dit |" not in md


@pytest.mark.slow
def test_dit_torch_vs_onnxruntime_dry_run(gpu_check, tmp_path):
    """The opt-in ONNX item end to end on the CPU: tiny config, torch fp32 vs its ONNX export on onnxruntime; the
    default DiT item times torch only and says where the export went."""
    ctx = {"device": "cpu", "dry_run": True, "quick": True, "work": str(tmp_path), "cap": 100}
    plain = gpu_check.item_dit(ctx)
    assert plain["status"] == "ok" and plain["ort"]["status"] == "not run" and "dit-onnx" in plain["ort"]["reason"]
    assert "export_s" not in plain and not list(tmp_path.glob("*.onnx"))
    res = gpu_check.item_dit_onnx(ctx)
    assert res["status"] == "ok" and res["config"] == "tiny"
    assert res["ort"]["providers"] == ["CPUExecutionProvider"]
    assert res["ort_vs_torch_max_rel_diff"] < 1e-4  # same weights, fp32 on both
    assert res["torch"]["median_s"] > 0 and res["export_s"] > 0


@pytest.mark.subprocess  # gpu_check runs each item in a child Python
def test_item_subprocess_failure_and_timeout_are_recorded(gpu_check, tmp_path):
    ctx = {"device": "cpu", "dry_run": True, "quick": True, "work": str(tmp_path)}
    r = gpu_check.run_item_subprocess("training", ctx, 120)
    assert r["status"] == "skipped" and r["wall_s"] > 0  # the child's JSON comes back
    r = gpu_check.run_item_subprocess("vggt", ctx, 0.5)  # cannot even import torch in time
    assert r["status"] == "timeout" and r["cap_s"] == 0.5


@pytest.mark.slow
def test_full_size_dits_wire_up_on_the_meta_device(gpu_check, tmp_path):
    """The GPU run's own configs and inputs (Wan-1.3B width at 81 x 256², Fun-Camera 1.3B; below VGGT-1B on
    25 x 518², MoGe-2 ViT-L, Difix at SD-Turbo size) go through the items' forward passes on the meta device:
    shapes only, nothing timed."""
    ctx = {"device": "meta", "dry_run": False, "quick": False, "work": str(tmp_path), "cap": 100}
    dit = gpu_check.item_dit(ctx)
    assert dit["status"] == "ok" and dit["config"] == "wan-1.3b" and dit["output_shape"] == [2, 16, 21, 32, 32]
    fun = gpu_check.item_fun_camera(ctx)
    assert fun["status"] == "ok" and fun["output_shape"] == [2, 16, 21, 32, 32]


@pytest.mark.slow
def test_full_size_geometry_and_refiner_wire_up_on_the_meta_device(gpu_check, tmp_path):
    ctx = {"device": "meta", "dry_run": False, "quick": False, "work": str(tmp_path), "cap": 100}
    vggt = gpu_check.item_vggt(ctx)
    assert vggt["status"] == "ok" and vggt["frames"] == 25 and vggt["size"] == 518 and vggt["parameters"] > 9e8
    moge = gpu_check.item_moge(ctx)
    assert moge["status"] == "ok" and moge["tokens"] == 37 * 37 and moge["parameters"] > 3e8
    difix = gpu_check.item_difix(ctx)
    assert difix["status"] == "ok" and difix["size"] == 512 and difix["parameters"] > 9e8


def test_failed_imports_are_reported_as_such(gpu_check, tmp_path, monkeypatch):
    """A missing navcrafter (the tree not importable) or a missing dependency is a failed import naming the module,
    never 'does not exist yet'; a fun-camera module that really is absent is 'not built'."""
    import importlib

    real_import = importlib.import_module

    def no_navcrafter(name, *a, **k):
        if name.startswith("navcrafter"):
            raise ModuleNotFoundError("No module named 'navcrafter'", name="navcrafter")
        return real_import(name, *a, **k)

    ctx = {"device": "cpu", "dry_run": True, "quick": True, "work": str(tmp_path), "cap": 100}
    monkeypatch.setattr(importlib, "import_module", no_navcrafter)
    with pytest.raises(ModuleNotFoundError) as exc:
        gpu_check.item_fun_camera(ctx)
    r = gpu_check.item_error(exc.value)
    assert r["status"] == "import error" and r["missing_module"] == "navcrafter"
    assert "run_check.sh" in r["reason"] and "does not exist" not in r["reason"]

    def no_funcamera(name, *a, **k):
        if name == "navcrafter.models.synthesis.funcamera":
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return real_import(name, *a, **k)

    monkeypatch.setattr(importlib, "import_module", no_funcamera)
    assert gpu_check.item_fun_camera(ctx)["status"] == "not built"
    monkeypatch.undo()

    r = gpu_check.item_error(ModuleNotFoundError("No module named 'pydantic'", name="pydantic"))
    assert r["status"] == "import error" and r["missing_module"] == "pydantic" and "wheels.txt" in r["reason"]


def test_results_written_after_every_item_and_deadline(gpu_check, tmp_path, monkeypatch):
    """results.json / results.md are rewritten after each item (a kill keeps what was measured); past the run's
    deadline an item is 'not run' with the reason; a composition failure is recorded, not fatal."""
    seen = []
    monkeypatch.setitem(gpu_check.FUNCS, "moge", lambda ctx: {"status": "ok", "median_s": 0.5, "size": [1, 1],
                                                               "tokens": 1})
    monkeypatch.setitem(gpu_check.FUNCS, "scene", lambda ctx: {"status": "ok", "paper_settings": {}})
    ctx = {"device": "cpu", "dry_run": True, "quick": True, "work": str(tmp_path)}
    r = gpu_check.run_all(ctx, ["moge", "scene", "vggt"], inline=True, deadline=None,
                          on_item=lambda res: seen.append(list(res)))
    assert seen == [["moge"], ["moge", "scene"], ["moge", "scene", "vggt"]]
    assert r["scene"]["composed"]["status"] == "error" and "KeyError" in r["scene"]["composed"]["error"]
    import time

    r = gpu_check.run_all(ctx, ["moge", "vggt"], inline=True, deadline=time.time() + 5)
    assert r["moge"]["status"] == "not run" and "out of time" in r["moge"]["reason"]
    assert r["vggt"]["status"] == "not run"


def test_gsplat_not_built_is_reported_never_built_inside_an_item(gpu_check, tmp_path, monkeypatch):
    monkeypatch.setattr(gpu_check, "gsplat_state", lambda: {"installed": True, "built": False, "reason": "not built"})
    monkeypatch.setattr(gpu_check, "_bench_import", lambda name: pytest.fail("the item must not start gsplat"))
    r = gpu_check.item_gsplat({"device": "cuda", "dry_run": False, "quick": False, "work": str(tmp_path)})
    assert r["status"] == "not built" and r["reason"] == "not built"


def test_preflight_and_gsplat_build_without_cuda(gpu_check, tmp_path):
    """Here (no GPU): the CPU preflight passes its required checks (imports, torch) and reports the limits; the
    CUDA preflight fails fast naming the missing device; the gsplat build says why it did not build."""
    pf = gpu_check.preflight("cpu")
    checks = {c["check"]: c for c in pf["checks"]}
    assert pf["ok"], pf["fatal"]
    assert checks["import navcrafter.models.synthesis.camcontrol"]["ok"]
    assert not checks["gsplat built"]["ok"]
    pf = gpu_check.preflight("cuda")
    assert not pf["ok"] and any(f.startswith("cuda device") for f in pf["fatal"])
    assert gpu_check.main(["--preflight", "--out", str(tmp_path)]) == 3
    assert json.loads((tmp_path / "preflight.json").read_text())["ok"] is False
    res = gpu_check.build_gsplat()
    assert res["status"] in ("skipped", "error") and not res["built"]


def test_gsplat_build_keeps_what_a_killed_build_left(gpu_check, tmp_path, monkeypatch):
    """gsplat deletes its build folder before a fresh build (so a build killed at a cap starts over); the build
    step skips that one deletion, so ninja resumes from the objects. Played with a stand-in gsplat whose
    ``cuda._backend`` import does what gsplat 1.5.3's does: rmtree(build folder), then build gsplat_cuda.so."""
    import shutil

    import torch

    pkg = tmp_path / "fake" / "gsplat"
    (pkg / "cuda").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "cuda" / "__init__.py").write_text("")
    (pkg / "cuda" / "_backend.py").write_text(
        "import os, shutil\n"
        "from torch.utils.cpp_extension import _get_build_directory\n"
        "build = _get_build_directory('gsplat_cuda', verbose=False)\n"
        "shutil.rmtree(build)\n"
        "os.makedirs(build, exist_ok=True)\n"
        "open(os.path.join(build, 'gsplat_cuda.so'), 'w').write('built')\n"
        "_C = object()\n")
    monkeypatch.syspath_prepend(str(tmp_path / "fake"))
    for name in [m for m in sys.modules if m == "gsplat" or m.startswith("gsplat.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    monkeypatch.delenv("TORCH_CUDA_ARCH_LIST", raising=False)
    monkeypatch.delenv("MAX_JOBS", raising=False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda *a: (9, 0))
    left = tmp_path / "ext" / "gsplat_cuda" / "a_killed_build.o"
    left.parent.mkdir(parents=True)
    left.write_text("object")
    st = gpu_check.gsplat_state()
    assert st["installed"] and not st["built"] and "--build-gsplat" in st["reason"]
    rmtree = shutil.rmtree
    try:
        res = gpu_check.build_gsplat()
    finally:
        for name in [m for m in sys.modules if m == "gsplat" or m.startswith("gsplat.")]:
            del sys.modules[name]
    assert res["status"] == "ok" and res["built"] and res["arch"] == "9.0"
    assert left.read_text() == "object"  # the killed build's objects survived
    assert shutil.rmtree is rmtree
    assert gpu_check.build_gsplat()["note"] == "already built"


def test_gsplat_item_loads_with_the_build_steps_arch_flags(gpu_check, tmp_path, monkeypatch):
    """Without TORCH_CUDA_ARCH_LIST torch's JIT picks '9.0+PTX' for the card, not the build step's '9.0': another
    command line, so ninja would recompile every kernel inside the item's cap. The item sets the build's value."""
    import types

    import torch

    monkeypatch.delenv("TORCH_CUDA_ARCH_LIST", raising=False)
    monkeypatch.delenv("MAX_JOBS", raising=False)
    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda *a: (9, 0))
    monkeypatch.setattr(gpu_check, "gsplat_state", lambda: {"installed": True, "built": True})
    seen = {}

    def run(ns):
        seen["arch"] = os.environ.get("TORCH_CUDA_ARCH_LIST")
        return {"gsplat_fit": {"its_per_s": 1.0}}  # gsplat_fit.run's shape: no status of its own

    fake = types.SimpleNamespace(refuse_without_cuda=lambda: None, run=run, markdown=lambda r: "")
    monkeypatch.setattr(gpu_check, "_bench_import", lambda name: fake)
    r = gpu_check.item_gsplat({"device": "cuda", "dry_run": False, "quick": True, "work": str(tmp_path)})
    assert r["status"] == "ok" and seen["arch"] == "9.0"


def test_explore_says_why_it_cannot_run_without_the_flow_stack(gpu_check, tmp_path, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "open3d" else real(name, *a))
    r = gpu_check.item_scene({"device": "cuda", "dry_run": False, "quick": False, "work": str(tmp_path), "cap": 600,
                              "with_explore": True})
    assert r["status"] == "ok" and r["explore"]["status"] == "skipped" and "open3d" in r["explore"]["reason"]


def test_camera_mini_item_dry_run_from_prepared_scenes(gpu_check, tmp_path):
    """camera-mini (issue 32 item 4) runs from a scenes file rendered beforehand (the node has no open3d): without
    it the item says how to make it; with it, the miniature trains, samples and reports (tiny, CPU: plumbing)."""
    out, scenes = tmp_path / "out", tmp_path / "scenes" / "mini.pkl"
    argv = ["--out", str(out), "--device", "cpu", "--dry-run", "--inline", "--items", "camera-mini",
            "--camera-scenes", str(scenes)]
    assert gpu_check.main(argv) == 0
    r = json.loads((out / "results.json").read_text())["items"]["camera-mini"]
    assert r["status"] == "not built" and "--prepare-camera-scenes" in r["reason"]
    assert gpu_check.main(["--prepare-camera-scenes", "--dry-run", "--camera-scenes", str(scenes)]) == 0
    assert scenes.is_file()
    assert gpu_check.main(argv) == 0
    r = json.loads((out / "results.json").read_text())["items"]["camera-mini"]
    assert r["status"] == "ok", r
    assert r["setup"]["base_steps"] == 2 and r["setup"]["device"] == "cpu" and 0 <= r["trained"]["r_err"]
    assert set(r) >= {"trained", "untrained", "trained_wrong_cameras", "floor", "autoencoder_psnr"}
    assert (out / "camera-mini-turns.png").is_file()
    assert "| camera-mini | ok | direction accuracy" in (out / "results.md").read_text()
    # run as an item process runs it: every finished stage lands in its partial file (kept if the cap cuts it)
    partial = tmp_path / "camera-mini.partial.json"
    ctx = {"dry_run": True, "quick": False, "device": "cpu", "work": str(tmp_path / "work"), "out": None,
           "camera_scenes": str(scenes), "partial": str(partial)}
    assert gpu_check.item_camera_mini(ctx)["status"] == "ok"
    pr = json.loads(partial.read_text())
    assert pr["stages"][:2] == ["trained", "base mean video"] and "sampled trained" in pr["stages"]
    assert {"trained", "untrained", "trained_wrong_cameras", "base_final_loss"} <= set(pr)
    assert pr["trained"]["direction_accuracy"] == r["trained"]["direction_accuracy"]  # the same run again


@pytest.mark.subprocess
def test_a_timed_out_item_keeps_what_it_printed(gpu_check, tmp_path):
    """An item cut by its cap leaves its printed lines (items/<name>.log, the last lines in its result) instead of
    a bare "timeout": 2026-12-04's camera-mini run on the GPU timed out and said nothing of how far it got."""
    code = "import time; print('base step 100: loss 1.16', flush=True); time.sleep(60)"
    with pytest.raises(subprocess.TimeoutExpired) as exc:
        gpu_check.run_group([sys.executable, "-c", code], 5)
    log = gpu_check.keep_item_log("camera-mini", {"out": str(tmp_path)}, exc.value.output, exc.value.stderr)
    assert log["log_tail"] == ["base step 100: loss 1.16"]
    assert (tmp_path / "items" / "camera-mini.log").read_text().startswith("base step 100")
    assert gpu_check.keep_item_log("x", {"out": None}, "", None) == {}
