"""Exploration metrics (issue 30): seen, coverage at several thresholds, relative to d0, AUC, object region."""

from __future__ import annotations

import numpy as np
import pytest

from navcrafter.models.metrics.cloud import exploration_metrics, seen_mask


def _plane(n: int = 100, spacing: float = 0.01) -> np.ndarray:
    """Points on the plane z = 2 over [-0.5, 0.5)^2 (1 cm grid)."""
    g = (np.arange(n) - n / 2) * spacing
    x, y = np.meshgrid(g, g, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, 2.0)], 1)


def test_half_the_surface_gives_half_coverage_and_half_seen():
    ref = _plane()
    half = ref[ref[:, 0] < 0]
    seen = ref[:, 0] < 0
    m = exploration_metrics(half, ref, np.zeros(len(half)), d0_m=2.0, seen=seen)
    assert m["seen"] == pytest.approx(0.5, abs=0.01)
    for t in ("0.02", "0.05", "0.10"):  # the next column is within 1 cm: a little over half at every threshold
        assert 0.49 < m[f"coverage_at_{t}"] < 0.62
    assert m["coverage_at_0.02"] <= m["coverage_at_0.05"] <= m["coverage_at_0.10"]
    assert m["precision"] == 1.0 and m["fscore_at_0.02"] == pytest.approx(2 * m["coverage_at_0.02"] /
                                                                           (1 + m["coverage_at_0.02"]))
    assert 0.45 < m["coverage_auc"] < 0.62


def test_relative_thresholds_follow_d0_and_noise_lowers_precision():
    ref = _plane()
    shifted = ref + np.array([0.0, 0.0, 0.03])  # 3 cm off the surface everywhere
    m_small = exploration_metrics(shifted, ref, np.full(len(ref), 0.03), d0_m=1.0)   # 1 % of d0 = 1 cm
    m_big = exploration_metrics(shifted, ref, np.full(len(ref), 0.03), d0_m=10.0)    # 1 % of d0 = 10 cm
    assert m_small["coverage_rel_0.01"] == 0.0 and m_big["coverage_rel_0.01"] == 1.0
    assert m_small["coverage_at_0.02"] == 0.0 and m_small["coverage_at_0.05"] == 1.0
    assert m_small["precision"] == 0.0 and m_small["fscore_rel_0.02"] == 0.0
    assert m_small["coverage_auc"] < m_big["coverage_auc"]


def test_object_region_is_scored_alone():
    ref = _plane()
    region = (np.abs(ref[:, 0]) < 0.1) & (np.abs(ref[:, 1]) < 0.1)
    m = exploration_metrics(ref[~region], ref, np.zeros((~region).sum()), d0_m=2.0, seen=~region, region=region)
    assert m["coverage_at_0.10"] > 0.9  # the rest covers the whole within 10 cm
    assert m["object_coverage"] < 0.25 and m["object_seen"] == 0.0
    with pytest.raises(ValueError, match="d0_m"):
        exploration_metrics(ref, ref, np.zeros(len(ref)), d0_m=0.0)


def test_seen_mask_projects_and_respects_occlusion():
    ref = _plane()
    K = np.array([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]])
    # a camera at the origin looking down +z sees the plane at z = 2; mask its right half with a nearer surface
    depth = np.full((64, 64), 2.0)
    depth[:, 32:] = 1.0
    seen = seen_mask(ref, np.eye(4)[None], K, [depth])
    visible = ref[:, 0] < 0  # u = 50 x / 2 + 32 < 32
    assert seen[visible].mean() > 0.95 and not seen[~visible].any()
    # moved 2 m beside the plane and looking away: sees nothing
    away = np.eye(4)
    away[:3, 3] = [0, 0, 5.0]
    assert not seen_mask(ref, away[None], K, [np.full((64, 64), 2.0)]).any()
