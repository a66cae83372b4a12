"""FID / FVD: the Fréchet distance against closed forms, and the feature networks' layout and plumbing.

No pretrained weights exist on test machines: the networks are checked for the official state-dict layout
(key names and shapes) and, with *random* weights saved under the official file names, for loading and
output shapes. Values computed with random weights test plumbing only, never the metrics themselves.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from navcrafter.models.metrics.evalnets import MetricUnavailable
from navcrafter.models.metrics.evalnets.fidfvd import fid, fvd
from navcrafter.models.metrics.evalnets.frechet import (
    feature_statistics,
    frechet_distance,
    frechet_distance_from_features,
    trace_sqrt_product,
)
from navcrafter.models.metrics.evalnets.i3d import FVD_I3D, I3DFeatures, same_padding
from navcrafter.models.metrics.evalnets.inception import FID_INCEPTION, InceptionFeatures
from navcrafter.models.metrics.evalnets.weights import ENV_VAR

METHODS = ("sqrtm", "eigh")


def _spd(rng: np.random.Generator, d: int, rank: int | None = None) -> np.ndarray:
    a = rng.normal(size=(d, rank or d))
    return a @ a.T / d + (0.0 if rank else 0.1 * np.eye(d))


# --------------------------------------------------------------------------------------------------
# Fréchet distance: closed forms
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", METHODS)
def test_identical_statistics_give_zero(method: str) -> None:
    rng = np.random.default_rng(0)
    mu, sigma = rng.normal(size=16), _spd(rng, 16)
    assert frechet_distance(mu, sigma, mu, sigma, method=method) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("method", METHODS)
def test_diagonal_covariances(method: str) -> None:
    rng = np.random.default_rng(1)
    mu1, mu2 = rng.normal(size=8), rng.normal(size=8)
    a, b = rng.uniform(0.1, 3.0, size=8), rng.uniform(0.1, 3.0, size=8)
    expected = np.sum((mu1 - mu2) ** 2) + np.sum((np.sqrt(a) - np.sqrt(b)) ** 2)
    assert frechet_distance(mu1, np.diag(a), mu2, np.diag(b), method=method) == pytest.approx(expected, rel=1e-9)


@pytest.mark.parametrize("method", METHODS)
def test_commuting_covariances(method: str) -> None:
    # Same eigenvectors: (S1 S2)^(1/2) = Q diag(sqrt(a b)) Q^T, so FD = |dmu|^2 + sum (sqrt a - sqrt b)^2.
    rng = np.random.default_rng(2)
    q, _ = np.linalg.qr(rng.normal(size=(10, 10)))
    a, b = rng.uniform(0.1, 2.0, size=10), rng.uniform(0.1, 2.0, size=10)
    s1, s2 = q @ np.diag(a) @ q.T, q @ np.diag(b) @ q.T
    mu1, mu2 = rng.normal(size=10), rng.normal(size=10)
    expected = np.sum((mu1 - mu2) ** 2) + np.sum((np.sqrt(a) - np.sqrt(b)) ** 2)
    assert frechet_distance(mu1, s1, mu2, s2, method=method) == pytest.approx(expected, rel=1e-8)


@pytest.mark.parametrize("method", METHODS)
def test_translation_only(method: str) -> None:
    rng = np.random.default_rng(3)
    sigma, mu = _spd(rng, 12), rng.normal(size=12)
    shift = rng.normal(size=12)
    got = frechet_distance(mu, sigma, mu + shift, sigma, method=method)
    assert got == pytest.approx(float(shift @ shift), rel=1e-7, abs=1e-9)


def test_one_dimensional_gaussians() -> None:
    # W2^2 between N(m1, s1^2) and N(m2, s2^2) is (m1 - m2)^2 + (s1 - s2)^2; scalars are accepted.
    assert frechet_distance(1.0, 4.0, -2.0, 9.0) == pytest.approx(9.0 + 1.0)


@pytest.mark.parametrize("method", METHODS)
def test_symmetric(method: str) -> None:
    rng = np.random.default_rng(4)
    mu1, mu2, s1, s2 = rng.normal(size=20), rng.normal(size=20), _spd(rng, 20), _spd(rng, 20)
    d12 = frechet_distance(mu1, s1, mu2, s2, method=method)
    assert d12 > 0
    assert d12 == pytest.approx(frechet_distance(mu2, s2, mu1, s1, method=method), rel=1e-8)


def test_methods_agree_on_general_and_singular_covariances() -> None:
    rng = np.random.default_rng(5)
    s1, s2 = _spd(rng, 32), _spd(rng, 32)
    assert trace_sqrt_product(s1, s2, method="sqrtm") == pytest.approx(trace_sqrt_product(s1, s2, method="eigh"),
                                                                       rel=1e-8)
    # Few samples -> rank-deficient covariances and a singular product (the FID case with N < D).
    f1, f2 = rng.normal(size=(5, 32)), rng.normal(size=(6, 32))
    d_sqrtm = frechet_distance_from_features(f1, f2, method="sqrtm")
    d_eigh = frechet_distance_from_features(f1, f2, method="eigh")
    assert np.isfinite(d_sqrtm) and d_eigh > 0
    assert d_sqrtm == pytest.approx(d_eigh, rel=1e-4)
    assert frechet_distance_from_features(f1, f2, method="gram") == pytest.approx(d_eigh, rel=1e-9)
    for method in ("eigh", "gram"):
        assert frechet_distance_from_features(f1, f1, method=method) == pytest.approx(0.0, abs=1e-9)
    # The Gram route with many samples (non-singular covariances) and unequal counts.
    g1, g2 = rng.normal(size=(50, 8)) @ rng.normal(size=(8, 8)), rng.normal(size=(70, 8)) + 0.3
    assert frechet_distance_from_features(g1, g2, method="gram") == pytest.approx(
        frechet_distance_from_features(g1, g2, method="sqrtm"), rel=1e-9)


def test_statistics_of_samples_converge() -> None:
    rng = np.random.default_rng(6)
    mu1, mu2 = np.array([0.0, 1.0, -1.0]), np.array([0.5, 0.0, 0.0])
    s1, s2 = _spd(rng, 3), _spd(rng, 3)
    truth = frechet_distance(mu1, s1, mu2, s2)
    n = 200_000
    x1 = rng.multivariate_normal(mu1, s1, size=n)
    x2 = rng.multivariate_normal(mu2, s2, size=n)
    m, s = feature_statistics(x1)
    assert np.allclose(m, mu1, atol=0.02) and np.allclose(s, s1, atol=0.02)
    assert frechet_distance_from_features(x1, x2) == pytest.approx(truth, abs=0.02)


def test_feature_statistics_are_mean_and_unbiased_covariance() -> None:
    f = np.random.default_rng(7).normal(size=(9, 4))
    mu, sigma = feature_statistics(f)
    assert np.allclose(mu, f.mean(0))
    assert np.allclose(sigma, (f - mu).T @ (f - mu) / 8)
    with pytest.raises(ValueError, match="at least 2"):
        feature_statistics(f[:1])
    with pytest.raises(ValueError, match="same length|must be"):
        frechet_distance(np.zeros(3), np.eye(3), np.zeros(4), np.eye(4))


# --------------------------------------------------------------------------------------------------
# Missing weights
# --------------------------------------------------------------------------------------------------
def test_missing_weights_raise_metric_unavailable(tmp_path, monkeypatch) -> None:
    images = np.zeros((2, 32, 32, 3))
    videos = np.zeros((2, 16, 32, 32, 3))
    with pytest.raises(MetricUnavailable, match="pt_inception-2015-12-05-6726825d.pth"):
        InceptionFeatures.from_pretrained(tmp_path)
    with pytest.raises(MetricUnavailable, match="i3d_pretrained_400.pt"):
        I3DFeatures.from_pretrained(tmp_path)
    with pytest.raises(MetricUnavailable, match="FID is unavailable.*pt_inception-2015-12-05-6726825d.pth"):
        fid(images, images, weights_dir=tmp_path)
    with pytest.raises(MetricUnavailable, match="FVD is unavailable.*i3d_pretrained_400.pt"):
        fvd(videos, videos, weights_dir=tmp_path)
    monkeypatch.setenv(ENV_VAR, str(tmp_path))  # default folder from the environment
    with pytest.raises(MetricUnavailable, match=str(tmp_path)):
        fid(images, images)
    assert FID_INCEPTION.filename == "pt_inception-2015-12-05-6726825d.pth"
    assert FVD_I3D.filename == "i3d_pretrained_400.pt"


# --------------------------------------------------------------------------------------------------
# Architectures: the official state-dict layouts
# --------------------------------------------------------------------------------------------------
_BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
_INCEPTION_BRANCHES = {
    "A": ("branch1x1", "branch5x5_1", "branch5x5_2", "branch3x3dbl_1", "branch3x3dbl_2", "branch3x3dbl_3",
          "branch_pool"),
    "B": ("branch3x3", "branch3x3dbl_1", "branch3x3dbl_2", "branch3x3dbl_3"),
    "C": ("branch1x1", "branch7x7_1", "branch7x7_2", "branch7x7_3", "branch7x7dbl_1", "branch7x7dbl_2",
          "branch7x7dbl_3", "branch7x7dbl_4", "branch7x7dbl_5", "branch_pool"),
    "D": ("branch3x3_1", "branch3x3_2", "branch7x7x3_1", "branch7x7x3_2", "branch7x7x3_3", "branch7x7x3_4"),
    "E": ("branch1x1", "branch3x3_1", "branch3x3_2a", "branch3x3_2b", "branch3x3dbl_1", "branch3x3dbl_2",
          "branch3x3dbl_3a", "branch3x3dbl_3b", "branch_pool"),
}
_INCEPTION_BLOCKS = {"Mixed_5b": "A", "Mixed_5c": "A", "Mixed_5d": "A", "Mixed_6a": "B", "Mixed_6b": "C",
                     "Mixed_6c": "C", "Mixed_6d": "C", "Mixed_6e": "C", "Mixed_7a": "D", "Mixed_7b": "E",
                     "Mixed_7c": "E"}


def _inception_keys() -> set[str]:
    convs = ["Conv2d_1a_3x3", "Conv2d_2a_3x3", "Conv2d_2b_3x3", "Conv2d_3b_1x1", "Conv2d_4a_3x3"]
    convs += [f"{block}.{b}" for block, kind in _INCEPTION_BLOCKS.items() for b in _INCEPTION_BRANCHES[kind]]
    assert len(convs) == 94  # Inception-v3 without the auxiliary head has 94 conv layers
    keys = {f"{c}.conv.weight" for c in convs} | {f"{c}.bn.{b}" for c in convs for b in _BN}
    return keys | {"fc.weight", "fc.bias"}


def test_inception_state_dict_matches_official_layout() -> None:
    sd = InceptionFeatures().state_dict()
    assert set(sd) == _inception_keys()
    expected = {
        "Conv2d_1a_3x3.conv.weight": (32, 3, 3, 3),
        "Conv2d_1a_3x3.bn.running_mean": (32,),
        "Conv2d_2a_3x3.conv.weight": (32, 32, 3, 3),
        "Conv2d_2b_3x3.conv.weight": (64, 32, 3, 3),
        "Conv2d_3b_1x1.conv.weight": (80, 64, 1, 1),
        "Conv2d_4a_3x3.conv.weight": (192, 80, 3, 3),
        "Mixed_5b.branch1x1.conv.weight": (64, 192, 1, 1),
        "Mixed_5b.branch5x5_2.conv.weight": (64, 48, 5, 5),
        "Mixed_5b.branch_pool.conv.weight": (32, 192, 1, 1),
        "Mixed_5d.branch_pool.conv.weight": (64, 288, 1, 1),
        "Mixed_6a.branch3x3.conv.weight": (384, 288, 3, 3),
        "Mixed_6b.branch7x7_2.conv.weight": (128, 128, 1, 7),
        "Mixed_6b.branch7x7dbl_2.conv.weight": (128, 128, 7, 1),
        "Mixed_6e.branch7x7dbl_5.conv.weight": (192, 192, 1, 7),
        "Mixed_7a.branch3x3_2.conv.weight": (320, 192, 3, 3),
        "Mixed_7b.branch3x3dbl_1.conv.weight": (448, 1280, 1, 1),
        "Mixed_7c.branch3x3_2b.conv.weight": (384, 384, 3, 1),
        "Mixed_7c.branch_pool.conv.weight": (192, 2048, 1, 1),
        "fc.weight": (1008, 2048),
        "fc.bias": (1008,),
    }
    for k, shape in expected.items():
        assert tuple(sd[k].shape) == shape, k
    # torchvision's Inception-v3 has 27,161,264 parameters; minus the auxiliary head (3,326,696) and with 1008
    # instead of 1000 classes (+8 x 2049) that is the FID network's 23,850,960.
    assert sum(p.numel() for p in InceptionFeatures().parameters()) == 27_161_264 - 3_326_696 + 8 * 2049
    bn = InceptionFeatures().Mixed_6b.branch1x1.bn
    assert bn.eps == pytest.approx(1e-3)


def test_inception_pools_are_the_fid_variants() -> None:
    from navcrafter.models.metrics.evalnets.inception import _avg3

    # count_include_pad=False: averaging ones stays one at the border.
    assert torch.equal(_avg3(torch.ones(1, 1, 5, 5)), torch.ones(1, 1, 5, 5))
    net = InceptionFeatures()
    assert (net.Mixed_7b.pool, net.Mixed_7c.pool) == ("avg", "max")


def _i3d_keys() -> set[str]:
    units = ["Conv3d_1a_7x7", "Conv3d_2b_1x1", "Conv3d_2c_3x3"]
    mixed = ["Mixed_3b", "Mixed_3c", "Mixed_4b", "Mixed_4c", "Mixed_4d", "Mixed_4e", "Mixed_4f", "Mixed_5b",
             "Mixed_5c"]
    units += [f"{m}.{b}" for m in mixed for b in ("b0", "b1a", "b1b", "b2a", "b2b", "b3b")]
    keys = {f"{u}.conv3d.weight" for u in units} | {f"{u}.bn.{b}" for u in units for b in _BN}
    return keys | {"logits.conv3d.weight", "logits.conv3d.bias"}


def test_i3d_state_dict_matches_official_layout() -> None:
    sd = I3DFeatures().state_dict()
    assert set(sd) == _i3d_keys()
    expected = {
        "Conv3d_1a_7x7.conv3d.weight": (64, 3, 7, 7, 7),
        "Conv3d_1a_7x7.bn.running_mean": (64,),
        "Conv3d_2b_1x1.conv3d.weight": (64, 64, 1, 1, 1),
        "Conv3d_2c_3x3.conv3d.weight": (192, 64, 3, 3, 3),
        "Mixed_3b.b0.conv3d.weight": (64, 192, 1, 1, 1),
        "Mixed_3b.b1a.conv3d.weight": (96, 192, 1, 1, 1),
        "Mixed_3b.b1b.conv3d.weight": (128, 96, 3, 3, 3),
        "Mixed_3b.b2b.conv3d.weight": (32, 16, 3, 3, 3),
        "Mixed_3b.b3b.conv3d.weight": (32, 192, 1, 1, 1),
        "Mixed_3c.b0.conv3d.weight": (128, 256, 1, 1, 1),
        "Mixed_4b.b0.conv3d.weight": (192, 480, 1, 1, 1),
        "Mixed_4f.b3b.conv3d.weight": (128, 528, 1, 1, 1),
        "Mixed_5b.b0.conv3d.weight": (256, 832, 1, 1, 1),
        "Mixed_5c.b2b.conv3d.weight": (128, 48, 3, 3, 3),
        "Mixed_5c.b3b.bn.running_var": (128,),
        "logits.conv3d.weight": (400, 1024, 1, 1, 1),
        "logits.conv3d.bias": (400,),
    }
    for k, shape in expected.items():
        assert tuple(sd[k].shape) == shape, k
    assert I3DFeatures().Mixed_4c.b1b.bn.eps == pytest.approx(1e-3)


def test_tf_same_padding() -> None:
    # TF "SAME": output ceil(n / s), total padding (out - 1) s + k - n, the odd pixel at the end.
    assert same_padding((16, 224, 224), (7, 7, 7), (2, 2, 2)) == (2, 3, 2, 3, 2, 3)
    assert same_padding((8, 112, 112), (1, 3, 3), (1, 2, 2)) == (0, 1, 0, 1, 0, 0)
    assert same_padding((4, 14, 14), (2, 2, 2), (2, 2, 2)) == (0, 0, 0, 0, 0, 0)
    assert same_padding((3, 7, 7), (3, 3, 3), (1, 1, 1)) == (1, 1, 1, 1, 1, 1)
    with pytest.raises(ValueError, match="at least 9 frames"):
        I3DFeatures()(torch.zeros(1, 3, 8, 224, 224))


# --------------------------------------------------------------------------------------------------
# Plumbing with random weights saved under the official file names
# --------------------------------------------------------------------------------------------------
def _randomise(model: nn.Module, seed: int) -> nn.Module:
    """He-initialised convolutions and random BatchNorm statistics, so features are O(1) (torch's default
    init shrinks activations through 94 layers to ~1e-8). Random weights: plumbing tests only."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, (nn.Conv2d, nn.Conv3d, nn.Linear)):
                fan_in = m.weight[0].numel()
                m.weight.copy_(torch.randn(m.weight.shape, generator=g) * (2.0 / fan_in) ** 0.5)
            elif isinstance(m, (nn.BatchNorm2d, nn.BatchNorm3d)):
                m.running_mean.copy_(0.1 * torch.randn(m.running_mean.shape, generator=g))
                m.running_var.copy_(torch.rand(m.running_var.shape, generator=g) + 0.5)
    return model


@pytest.fixture(scope="module")
def random_weights(tmp_path_factory) -> tuple:
    folder = tmp_path_factory.mktemp("eval-weights")
    inception, i3d = _randomise(InceptionFeatures(), 0), _randomise(I3DFeatures(), 1)
    torch.save(inception.state_dict(), folder / FID_INCEPTION.filename)
    torch.save(i3d.state_dict(), folder / FVD_I3D.filename)
    return folder, inception.state_dict(), i3d.state_dict()


def test_inception_loads_official_file_and_gives_features(random_weights) -> None:
    folder, saved, _ = random_weights
    net = InceptionFeatures.from_pretrained(folder)
    assert not net.training
    loaded = net.state_dict()
    assert all(torch.equal(loaded[k], saved[k]) for k in saved)
    rng = np.random.default_rng(0)
    images = rng.uniform(size=(2, 40, 56, 3))
    f = net.fid_features(images)
    assert f.shape == (2, 2048) and f.dtype == np.float64 and np.isfinite(f).all()
    assert f.std() > 1e-3
    # uint8 input and a list of differently sized images go through the same preprocessing
    f8 = net.fid_features((images * 255).round().astype(np.uint8))
    assert np.allclose(f8, f, rtol=0.05, atol=0.05 * np.abs(f).max())
    assert net.fid_features([images[0], images[1, :30]]).shape == (2, 2048)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        net.fid_features(images * 255)


def test_fid_plumbing_with_random_weights(random_weights) -> None:
    # Random weights: this checks the wiring (loading, features, statistics, distance), not FID values.
    folder = random_weights[0]
    rng = np.random.default_rng(1)
    x, y = rng.uniform(size=(2, 32, 32, 3)), rng.uniform(size=(2, 32, 32, 3)) ** 3
    # method="gram": scipy's sqrtm of a 2048x2048 matrix takes ~25 s on 2 cores (same value, tested above).
    same = fid(x, x, weights_dir=folder, method="gram")
    other = fid(x, y, weights_dir=folder, method="gram")
    assert isinstance(same, float) and isinstance(other, float)
    assert other > 0
    assert abs(same) <= 1e-6 * other


def test_i3d_loading_is_strict(random_weights, tmp_path) -> None:
    _, _, saved = random_weights
    # Files from old PyTorch versions lack num_batches_tracked: accepted.
    old = {k: v for k, v in saved.items() if not k.endswith("num_batches_tracked")}
    torch.save(old, tmp_path / FVD_I3D.filename)
    net = I3DFeatures.from_pretrained(tmp_path)
    assert torch.equal(net.state_dict()["logits.conv3d.weight"], saved["logits.conv3d.weight"])
    # A missing tensor, a wrong shape or a non-state-dict file: unavailable, never partly random.
    broken = dict(old)
    del broken["Mixed_4d.b1b.conv3d.weight"]
    torch.save(broken, tmp_path / FVD_I3D.filename)
    with pytest.raises(MetricUnavailable, match="missing: Mixed_4d.b1b.conv3d.weight"):
        I3DFeatures.from_pretrained(tmp_path)
    broken = dict(old, **{"logits.conv3d.bias": torch.zeros(101)})
    torch.save(broken, tmp_path / FVD_I3D.filename)
    with pytest.raises(MetricUnavailable, match="logits.conv3d.bias"):
        I3DFeatures.from_pretrained(tmp_path)
    (tmp_path / FVD_I3D.filename).write_bytes(b"not a checkpoint")
    with pytest.raises(MetricUnavailable, match="cannot read"):
        I3DFeatures.from_pretrained(tmp_path)


@pytest.mark.slow
def test_fvd_plumbing_with_random_weights(random_weights) -> None:
    # Random weights: this checks the wiring (loading, features, statistics, distance), not FVD values.
    folder, _, saved = random_weights
    net = I3DFeatures.from_pretrained(folder / FVD_I3D.filename)  # the file itself is accepted too
    assert all(torch.equal(net.state_dict()[k], saved[k]) for k in saved)
    # 10 frames (I3D needs >= 9; FVD uses 16) of 112x112, resized to 224x224 inside: keeps the test fast.
    videos = np.random.default_rng(2).uniform(size=(2, 10, 112, 112, 3)).astype(np.float32)
    f = net.fvd_features(videos)
    assert f.shape == (2, 400) and np.isfinite(f).all() and f.std() > 1e-3
    same = fvd(videos, videos, weights_dir=folder)
    assert isinstance(same, float)
    assert abs(same) <= 1e-4 * max(1.0, float(np.var(f, axis=0, ddof=1).sum()))
