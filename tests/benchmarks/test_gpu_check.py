"""benchmarks/gpu_check.py without a GPU: the refusal, and the plumbing in its CPU dry run (tiny configs; its
numbers are not measurements)."""

from __future__ import annotations

import json

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
    assert set(gpu_check.ITEMS) == set(gpu_check.FUNCS)


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
    """The DiT item end to end on the CPU: tiny config, torch fp32 vs its ONNX export on onnxruntime."""
    ctx = {"device": "cpu", "dry_run": True, "quick": True, "work": str(tmp_path), "cap": 100}
    res = gpu_check.item_dit(ctx)
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
