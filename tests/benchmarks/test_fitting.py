"""benchmarks/fitting.py's sparse-view protocol (--views): the results' shape and paired effects on made-up
records, and the whole protocol on one tiny scene (slow)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def fb():
    sys.path.insert(0, str(ROOT / "benchmarks"))  # the script imports its sibling seeds.py
    spec = importlib.util.spec_from_file_location("fitting_bench", ROOT / "benchmarks" / "fitting.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["fitting_bench"] = mod
    spec.loader.exec_module(mod)
    return mod


def _row(photo, views, variant, psnr, absrel, converged=True):
    return {"photo": photo, "kind": photo.split("-")[0], "seed": 10, "views": views, "variant": variant,
            "psnr": psnr, "ssim": 0.5, "depth_absrel": absrel, "lpips": None, "converged": converged,
            "heldout_l1_change_last20": 0.01, "heldout_l1_at_60_80_100": [0.2, 0.1, 0.1], "iterations": 10,
            "n_gaussians": 5, "visible_fraction": 0.8, "align_rmse": 0.0, "train_seconds": 1.0}


def test_results_shape_and_paired_effects(fb):
    rows = []
    for photo, gain in (("room-10.png", 0.5), ("street-10.png", -0.1), ("tabletop-10.png", 0.3)):
        for v in (3, 6):
            rows += [_row(photo, v, "none", 20.0, 0.20), _row(photo, v, "depth", 20.0 + gain, 0.15),
                     _row(photo, v, "dropgaussian", 20.0 + gain, 0.15, converged=False),
                     _row(photo, v, "longer", 21.0, 0.1), _row(photo, v, "refine", 21.5, 0.1)]
    res = fb.sparse_results(rows, {"quick": True})
    assert set(res) == {"protocol", "views", "paired"}
    assert set(res["views"]) == set(res["paired"]) == {"3", "6"}
    assert {"psnr", "ssim", "depth_absrel"} <= set(res["views"]["3"]["none"])
    assert res["views"]["3"]["dropgaussian"]["converged"] == 0
    assert len(res["views"]["3"]["none"]["fits"]) == 3
    d = res["paired"]["3"]["depth"]
    assert {"delta_psnr", "delta_depth_absrel", "se", "wins", "n"} <= set(d)
    assert d["delta_psnr"] == pytest.approx((0.5 - 0.1 + 0.3) / 3)
    assert d["delta_depth_absrel"] == pytest.approx(-0.05)
    assert d["wins"] == 2 and d["n"] == 3 and d["wins_depth"] == 3
    assert d["se"] == pytest.approx(0.1764, abs=1e-3)  # std (n-1) of (0.5, -0.1, 0.3) / sqrt 3
    assert res["paired"]["3"]["dropgaussian"]["delta_psnr"] == pytest.approx(0.0)
    assert res["paired"]["3"]["refine"]["delta_psnr"] == pytest.approx(0.5)
    assert "oracle_depth" not in res["paired"]["3"]  # no such records, no pair


def test_merge_pools_the_fits_of_runs_over_other_seeds(fb):
    proto = {"quick": True, "views": [3], "kinds": ["room"], "development": False, "complete": True, "seeds": [0, 0]}
    runs = []
    for photo, gain in (("room-10.png", 0.4), ("room-11.png", -0.2)):
        rows = [_row(photo, 3, "none", 20.0, 0.2), _row(photo, 3, "depth", 20.0 + gain, 0.1)]
        for r in rows:
            r["seed"] = int(photo[5:7])
        runs.append(fb.sparse_results(rows, dict(proto)))
    res = fb.merge_sparse(runs)
    assert res["paired"]["3"]["depth"]["n"] == 2 and res["paired"]["3"]["depth"]["wins"] == 1
    assert res["paired"]["3"]["depth"]["delta_psnr"] == pytest.approx(0.1)
    assert res["protocol"]["seeds"] == [10, 11] and res["protocol"]["n_scenes"] == 2
    with pytest.raises(ValueError, match="two of the merged runs"):
        fb.merge_sparse([runs[0], runs[0]])
    six = fb.sparse_results([{**r, "views": 6} for r in runs[0]["views"]["3"]["none"]["fits"]
                             for r in [dict(r, variant="none")]], dict(proto, views=[6]))
    both = fb.merge_sparse([res, six])  # view counts pool too: one table with both
    assert set(both["views"]) == {"3", "6"} and both["protocol"]["views"] == [3, 6]
    assert both["paired"]["3"]["depth"]["n"] == 2
    runs[1]["protocol"]["lambda_depth"] = 0.5
    with pytest.raises(ValueError, match="lambda_depth"):
        fb.merge_sparse(runs)


@pytest.mark.slow
def test_tiny_run_writes_the_table(fb, tmp_path):
    out = tmp_path / "out"
    assert fb.main(["--out", str(out), "--quick", "--views", "3", "--seeds", "0-0", "--kinds", "room",
                    "--fit-iterations", "10"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert set(res) == {"protocol", "views", "paired"}
    assert res["protocol"]["complete"] and res["protocol"]["development"]
    assert set(res["views"]["3"]) == set(fb.SPARSE_VARIANTS)
    for s in res["views"]["3"].values():
        assert s["n"] == 1 and 0 < s["visible_fraction"] <= 1
        f = s["fits"][0]
        assert len(f["heldout_l1_at_60_80_100"]) == 3 and isinstance(f["converged"], bool)
        assert 0 < s["depth_absrel"] < 10 and 0 < s["psnr"] < 60
    assert set(res["paired"]["3"]) == set(fb.PAIRS)
    assert res["views"]["3"]["longer"]["fits"][0]["iterations"] == 10 + 10
    assert "sparse views" in (out / "results.md").read_text()


def test_hallucinated_training_pixels_witness_nothing(fb, monkeypatch):
    """A test pixel counts as seen only through training pixels whose generated frame showed the truth there."""
    import numpy as np

    from navcrafter.tasks import readers

    true = np.full((8, 8), 2.0)
    hallucinated = true.copy()
    hallucinated[:, :4] = 3.0  # the video model put the left half 1 m further away
    shown = {0: true, 1: hallucinated}
    monkeypatch.setattr(readers, "frame_truth", lambda scene, k, idx: (None, [shown[idx[0]]]))
    sc = object.__new__(fb.SparseScene)
    sc.scene, sc.refs, sc.h, sc.w = None, [(1, 0), (1, 1), (2, 0)], 8, 8
    sc._true_depth = {0: true, 1: true}
    sc.true_c2w = np.stack([np.eye(4)] * 3)
    sc.K = np.stack([np.array([[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]])] * 3)
    sc.test, sc.test_depth = np.array([2]), [true]
    assert fb.SparseScene.shown_truthfully(sc, 0).all()
    half = fb.SparseScene.shown_truthfully(sc, 1)
    assert not half[:, :4].any() and half[:, 4:].all()
    (m,) = fb.SparseScene.masks(sc, np.array([1]))
    assert not m[:, :4].any() and m[:, 4:].all()
    (m,) = fb.SparseScene.masks(sc, np.array([0, 1]))
    assert m.all()


def test_lambda_grid_names_each_space(fb):
    """``--lambda-grid``: plain entries tune in the run's depth space, ``space:lambda`` in another; an unknown
    space is refused with the fix."""
    assert fb.parse_grid(None, "median") == tuple(("median", x) for x in fb.LAMBDA_GRID)
    grid = fb.parse_grid("1, relative:2", "median")
    assert grid == (("median", 1.0), ("relative", 2.0))
    assert [fb.grid_name(s, x, "median") for s, x in grid] == ["depth@1", "depth@relative:2"]
    assert fb.grid_name("relative", 2.0, "relative") == "depth@2"
    with pytest.raises(SystemExit, match="depth space"):
        fb.parse_grid("inverse:1", "median")
