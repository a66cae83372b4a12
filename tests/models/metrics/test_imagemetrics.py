"""Image metrics: PSNR/SSIM known values, and LPIPS architecture, weight loading and distance properties.

LPIPS is exercised with randomly initialised networks saved in the official file layouts (no pretrained
weights are available offline); the real values need the official files.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from navcrafter.models.metrics import image as M
from navcrafter.models.metrics.evalnets import WEIGHT_FILES, MetricUnavailable, weights
from navcrafter.models.metrics.evalnets import lpips as L

rng = np.random.default_rng(0)


# --------------------------------------------------------------------------------------------------
# PSNR
# --------------------------------------------------------------------------------------------------
def test_psnr_identical_is_inf():
    a = rng.random((16, 16, 3))
    assert M.psnr(a, a) == np.inf
    assert np.all(M.psnr(np.stack([a, a]), np.stack([a, a])) == np.inf)


def test_psnr_constant_offset_closed_form():
    a = 0.1 + 0.8 * rng.random((20, 24, 3))
    d = 0.05
    assert M.psnr(a, a + d) == pytest.approx(10 * np.log10(1 / d**2))  # 26.0206 dB
    assert M.psnr(a, a + d) == pytest.approx(26.0206, abs=1e-4)
    assert M.psnr(255 * a, 255 * (a + d), data_range=255) == pytest.approx(10 * np.log10(1 / d**2))


def test_psnr_batch_and_torch():
    a = rng.random((3, 8, 8, 3))
    b = a.copy()
    b[1] += 0.1
    b[2] -= 0.01
    got = M.psnr(a, b)
    assert got.shape == (3,)
    np.testing.assert_allclose(got, [np.inf, 20.0, 40.0])
    assert M.psnr(torch.from_numpy(a[1]), torch.from_numpy(b[1])) == pytest.approx(20.0)
    with pytest.raises(ValueError, match="same shape"):
        M.psnr(a, b[:2])


# --------------------------------------------------------------------------------------------------
# SSIM
# --------------------------------------------------------------------------------------------------
def test_ssim_identical_is_one():
    a = rng.random((32, 40, 3))
    assert M.ssim(a, a) == pytest.approx(1.0, abs=1e-12)


def test_ssim_constant_images_closed_form():
    # No variance: SSIM = (2 m1 m2 + C1) / (m1^2 + m2^2 + C1) at every pixel.
    c1 = 0.01**2
    expected = (2 * 0.5 * 0.25 + c1) / (0.5**2 + 0.25**2 + c1)  # 0.2501 / 0.3126
    assert expected == pytest.approx(0.800064, abs=1e-6)
    assert M.ssim(np.full((16, 16, 3), 0.5), np.full((16, 16, 3), 0.25)) == pytest.approx(expected, abs=1e-12)


def test_ssim_single_window_by_hand():
    # An 11x11 image has exactly one valid window: weighted statistics with the 2-D Gaussian w = g g^T.
    a = rng.random((11, 11, 3))
    b = np.clip(0.7 * a + 0.2 + 0.05 * rng.standard_normal(a.shape), 0, 1)
    x = np.arange(11) - 5.0
    g = np.exp(-(x**2) / (2 * 1.5**2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01**2, 0.03**2
    per_channel = []
    for ch in range(3):
        p, q = a[..., ch], b[..., ch]
        mp, mq = (w * p).sum(), (w * q).sum()
        vp, vq = (w * p * p).sum() - mp**2, (w * q * q).sum() - mq**2
        cov = (w * p * q).sum() - mp * mq
        per_channel.append((2 * mp * mq + c1) * (2 * cov + c2) / ((mp**2 + mq**2 + c1) * (vp + vq + c2)))
    assert M.ssim(a, b) == pytest.approx(np.mean(per_channel), abs=1e-12)


def test_ssim_symmetric_and_decreasing_with_noise():
    a = rng.random((48, 48, 3))
    noisy = [np.clip(a + s * rng.standard_normal(a.shape), 0, 1) for s in (0.02, 0.1, 0.3)]
    values = [M.ssim(a, n) for n in noisy]
    assert values[0] > values[1] > values[2]
    assert all(-1 <= v < 1 for v in values)
    assert M.ssim(noisy[1], a) == pytest.approx(values[1], abs=1e-12)


def test_ssim_batch_map_and_kernel():
    a, b = rng.random((2, 20, 30, 3)), rng.random((2, 20, 30, 3))
    got = M.ssim(a, b)
    assert got.shape == (2,)
    np.testing.assert_allclose(got, [M.ssim(a[0], b[0]), M.ssim(a[1], b[1])])
    assert M.ssim_map(a, b).shape == (2, 10, 20, 3)
    g = M.gaussian_kernel_1d()
    assert g.shape == (11,) and g.sum() == pytest.approx(1.0) and g.argmax() == 5
    assert M.ssim(torch.from_numpy(a[0]), torch.from_numpy(b[0])) == pytest.approx(got[0])
    with pytest.raises(ValueError, match="at least 11x11"):
        M.ssim(a[:, :10], b[:, :10])


# --------------------------------------------------------------------------------------------------
# LPIPS: layouts
# --------------------------------------------------------------------------------------------------
ALEX_CONVS = {0: (64, 3, 11, 11), 3: (192, 64, 5, 5), 6: (384, 192, 3, 3), 8: (256, 384, 3, 3), 10: (256, 256, 3, 3)}
VGG_CONVS = {0: (64, 3), 2: (64, 64), 5: (128, 64), 7: (128, 128), 10: (256, 128), 12: (256, 256), 14: (256, 256),
             17: (512, 256), 19: (512, 512), 21: (512, 512), 24: (512, 512), 26: (512, 512), 28: (512, 512)}


def test_trunk_keys_match_torchvision_layout():
    alex = L.LPIPS("alex").trunk_state_dict()
    assert set(alex) == {f"features.{i}.{p}" for i in (0, 3, 6, 8, 10) for p in ("weight", "bias")}
    for i, shape in ALEX_CONVS.items():
        assert tuple(alex[f"features.{i}.weight"].shape) == shape
        assert tuple(alex[f"features.{i}.bias"].shape) == shape[:1]
    vgg = L.LPIPS("vgg").trunk_state_dict()
    assert set(vgg) == {f"features.{i}.{p}" for i in VGG_CONVS for p in ("weight", "bias")}
    for i, (c_out, c_in) in VGG_CONVS.items():
        assert tuple(vgg[f"features.{i}.weight"].shape) == (c_out, c_in, 3, 3)


def test_lin_keys_match_lpips_v01_layout():
    for net, chans in (("alex", (64, 192, 384, 256, 256)), ("vgg", (64, 128, 256, 512, 512))):
        lin = L.LPIPS(net).lin_state_dict()
        assert set(lin) == {f"lin{k}.model.1.weight" for k in range(5)}
        for k, c in enumerate(chans):
            assert tuple(lin[f"lin{k}.model.1.weight"].shape) == (1, c, 1, 1)


def test_taps_are_relus_after_the_expected_convs():
    for net, convs in (("alex", ALEX_CONVS), ("vgg", VGG_CONVS)):
        trunk = L.LPIPS(net).net
        assert all(isinstance(trunk.features[i], torch.nn.Conv2d) for i in convs)
        assert sum(isinstance(m, torch.nn.Conv2d) for m in trunk.features) == len(convs)
        assert all(isinstance(trunk.features[t], torch.nn.ReLU) for t in trunk.taps)
    assert L.AlexNetFeatures.taps == (1, 4, 7, 9, 11)  # relu1..relu5
    assert L.VGG16Features.taps == (3, 8, 15, 22, 29)  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3


def test_weight_files_registered():
    assert WEIGHT_FILES["alexnet-torchvision"].filename == "alexnet-owt-7be5be79.pth"
    assert WEIGHT_FILES["vgg16-torchvision"].filename == "vgg16-397923af.pth"
    assert WEIGHT_FILES["lpips-alex-v0.1"].filename == "alex.pth"
    assert WEIGHT_FILES["lpips-vgg-v0.1"].filename == "vgg.pth"
    assert WEIGHT_FILES["alexnet-torchvision"].source == "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"
    assert "richzhang/PerceptualSimilarity" in WEIGHT_FILES["lpips-vgg-v0.1"].source


# --------------------------------------------------------------------------------------------------
# LPIPS: loading
# --------------------------------------------------------------------------------------------------
def random_lpips(net: str = "alex", seed: int = 0) -> L.LPIPS:
    torch.manual_seed(seed)
    model = L.LPIPS(net)
    with torch.no_grad():
        for lin in model.lins:  # the released heads are non-negative
            lin.model[1].weight.abs_()
    return model


def save_official(model: L.LPIPS, folder, trunk_extra: dict | None = None) -> None:
    trunk = model.trunk_state_dict() | (trunk_extra or {})
    torch.save(trunk, folder / L.TRUNK_WEIGHTS[model.net_name].filename)
    torch.save(model.lin_state_dict(), folder / L.LIN_WEIGHTS[model.net_name].filename)


@pytest.fixture()
def alex_dir(tmp_path):
    model = random_lpips("alex")
    # torchvision's file also holds the classifier, which LPIPS ignores.
    save_official(model, tmp_path, {"classifier.1.weight": torch.zeros(4, 9216), "classifier.1.bias": torch.zeros(4)})
    return tmp_path, model


def test_missing_weights_unavailable(tmp_path, monkeypatch):
    with pytest.raises(MetricUnavailable, match="alexnet-owt-7be5be79.pth"):
        L.LPIPS.from_pretrained("alex", tmp_path)
    torch.save(L.LPIPS("alex").trunk_state_dict(), tmp_path / "alexnet-owt-7be5be79.pth")
    with pytest.raises(MetricUnavailable, match=r"alex\.pth not found"):
        L.LPIPS.from_pretrained("alex", tmp_path)
    with pytest.raises(MetricUnavailable, match="vgg16-397923af.pth"):
        L.LPIPS.from_pretrained("vgg", tmp_path)
    monkeypatch.setenv(weights.ENV_VAR, str(tmp_path / "empty"))
    with pytest.raises(MetricUnavailable, match="never computes this metric with random weights"):
        L.lpips_distance(np.zeros((1, 64, 64, 3)), np.zeros((1, 64, 64, 3)))


def test_from_pretrained_loads_official_layout(alex_dir):
    folder, ref = alex_dir
    model = L.LPIPS.from_pretrained("alex", folder)
    assert not model.training
    assert not any(p.requires_grad for p in model.parameters())
    for k, v in (ref.trunk_state_dict() | ref.lin_state_dict()).items():
        torch.testing.assert_close(model.state_dict()[k.replace("features.", "net.features.")], v, rtol=0, atol=0)


def test_distance_properties(alex_dir):
    folder, _ = alex_dir
    model = L.LPIPS.from_pretrained("alex", folder)
    a = rng.random((3, 64, 64, 3)).astype(np.float32)
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1).astype(np.float32)
    same = L.lpips_distance(a, a, model=model)
    np.testing.assert_array_equal(same, np.zeros(3))
    d = L.lpips_distance(a, b, model=model)
    assert d.shape == (3,) and d.dtype == np.float64 and np.all(d > 0)
    np.testing.assert_allclose(L.lpips_distance(b, a, model=model), d, rtol=1e-5)
    np.testing.assert_allclose(L.lpips_distance(a, b, model=model, batch_size=2), d, rtol=1e-5)
    np.testing.assert_allclose(L.lpips_distance(a[1], b[1], model=model), d[1:2], rtol=1e-5)
    # Loading by name from the folder gives the same numbers.
    np.testing.assert_allclose(L.lpips_distance(a[:1], b[:1], "alex", folder), d[:1], rtol=1e-5)


def test_distance_matches_formula_with_unit_heads():
    # With all-ones heads: sum over taps of the spatial mean of |f0/|f0| - f1/|f1||^2, inputs 2x-1, scaled.
    torch.manual_seed(1)
    model = L.LPIPS("alex")
    with torch.no_grad():
        for lin in model.lins:
            lin.model[1].weight.fill_(1.0)
    a, b = torch.rand(2, 64, 64, 3), torch.rand(2, 64, 64, 3)
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)
    with torch.no_grad():
        f0 = model.net(((2 * a - 1).permute(0, 3, 1, 2) - shift) / scale)
        f1 = model.net(((2 * b - 1).permute(0, 3, 1, 2) - shift) / scale)
    expected = sum(((u / u.norm(dim=1, keepdim=True) - v / v.norm(dim=1, keepdim=True)) ** 2).sum(1).mean((1, 2))
                   for u, v in zip(f0, f1))
    np.testing.assert_allclose(L.lpips_distance(a.numpy(), b.numpy(), model=model), expected.numpy(), rtol=1e-4)


def test_vgg_roundtrip(tmp_path):
    ref = random_lpips("vgg")
    save_official(ref, tmp_path)
    model = L.LPIPS.from_pretrained("vgg", tmp_path)
    a = rng.random((1, 32, 32, 3)).astype(np.float32)
    b = rng.random((1, 32, 32, 3)).astype(np.float32)
    assert L.lpips_distance(a, a, model=model)[0] == 0.0
    d = L.lpips_distance(a, b, model=model)
    assert d[0] > 0
    np.testing.assert_allclose(d, L.lpips_distance(a, b, model=ref), rtol=1e-6)


# --------------------------------------------------------------------------------------------------
# LPIPS: bad files
# --------------------------------------------------------------------------------------------------
def test_corrupt_file_is_a_clear_error(alex_dir):
    folder, _ = alex_dir
    (folder / "alex.pth").write_bytes(b"this is not a checkpoint")
    with pytest.raises(L.WeightFileError, match=r"alex\.pth could not be read"):
        L.LPIPS.from_pretrained("alex", folder)
    torch.save([1, 2, 3], folder / "alex.pth")
    with pytest.raises(L.WeightFileError, match="not a state dict"):
        L.LPIPS.from_pretrained("alex", folder)
    assert issubclass(L.WeightFileError, MetricUnavailable)


def test_wrong_file_is_a_clear_error(alex_dir):
    folder, model = alex_dir
    torch.save(L.LPIPS("vgg").lin_state_dict(), folder / "alex.pth")  # vgg heads in place of alex heads
    with pytest.raises(L.WeightFileError, match=r"alex\.pth does not match.*wrong shapes: lin1\.model\.1\.weight"):
        L.LPIPS.from_pretrained("alex", folder)
    torch.save(model.lin_state_dict(), folder / "alex.pth")
    torch.save(model.trunk_state_dict(), folder / "vgg16-397923af.pth")  # alex trunk in place of vgg16
    torch.save(L.LPIPS("vgg").lin_state_dict(), folder / "vgg.pth")
    with pytest.raises(L.WeightFileError, match=r"vgg16-397923af\.pth does not match.*missing keys: features\.2\."):
        L.LPIPS.from_pretrained("vgg", folder)
    torch.save({"module." + k: v for k, v in model.trunk_state_dict().items()}, folder / "alexnet-owt-7be5be79.pth")
    with pytest.raises(L.WeightFileError, match=r"missing keys.*unexpected keys: module\.features\.0\.weight"):
        L.LPIPS.from_pretrained("alex", folder)
    with pytest.raises(ValueError, match="must be a folder"):
        L.LPIPS.from_pretrained("alex", folder / "alex.pth")
    with pytest.raises(ValueError, match="net must be one of"):
        L.LPIPS("squeeze")
