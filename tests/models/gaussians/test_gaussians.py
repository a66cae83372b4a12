"""3D Gaussian Splatting building blocks: the rasterizer against a brute-force reference, SH, the model,
the 3DGS PLY and DropGaussian. All scenes are tiny (the whole file runs in seconds on 2 cores)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from navcrafter.models.camera.cameras import invert_pose, look_at, project
from navcrafter.models.gaussians.dropgaussian import DropGaussian, drop_gaussians, drop_rate
from navcrafter.models.gaussians.model import GaussianModel
from navcrafter.models.gaussians.ply import load_ply, property_names, read_ply_header, save_ply, to_structured
from navcrafter.models.gaussians.rasterize import rasterization
from navcrafter.models.gaussians.reference import rasterize_reference
from navcrafter.models.gaussians.sh import SH_C0, SH_C1, SH_C2, SH_C3, sh_basis, sh_dc_to_rgb, sh_to_rgb

W, H = 40, 24  # not multiples of 16: partial tiles on two sides


@pytest.fixture(autouse=True, scope="module")
def _two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(min(before, 2))
    yield
    torch.set_num_threads(before)


def cameras(dtype=torch.float64, n=3, width=W, height=H):
    """``n`` OpenCV cameras around the origin-facing scene (viewmats = inverse poses) and their Ks."""
    eyes = [(0.0, 0.0, 0.0), (0.6, -0.3, 0.2), (-0.5, 0.4, -0.3), (0.2, 0.5, 0.4)][:n]
    viewmats = [invert_pose(look_at(np.array(e), np.array([0.0, 0.0, 3.0]))) for e in eyes]
    f = 0.8 * width
    K = np.array([[f, 0.0, width / 2], [0.0, f * 1.05, height / 2], [0.0, 0.0, 1.0]])
    return torch.tensor(np.stack(viewmats), dtype=dtype), torch.tensor(np.stack([K] * n), dtype=dtype)


def random_scene(n=60, seed=0, dtype=torch.float64, sh_degree=None):
    """Gaussians in front of the cameras, plus a few behind them, beyond the image and transparent."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=dtype) * torch.tensor([2.4, 1.6, 2.5], dtype=dtype)
    means = means + torch.tensor([-1.2, -0.8, 1.8], dtype=dtype)
    means[0, 2] = -1.0  # behind every camera
    means[1] = torch.tensor([30.0, 0.0, 3.0], dtype=dtype)  # far off-screen
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=dtype) * 1.5 - 3.0)
    opacities = torch.rand(n, generator=g, dtype=dtype) * 0.85 + 0.1
    opacities[2] = 0.0
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=g, dtype=dtype)
    else:
        colors = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=dtype) * 0.4
    return means, quats, scales, opacities, colors


def both(params, viewmats, Ks, **kw):
    out = rasterization(*params, viewmats, Ks, W, H, **kw)
    ref = rasterize_reference(*params, viewmats, Ks, W, H, **kw)
    return out, ref


# --------------------------------------------------------------------------------------------------
# Parity with the brute-force reference
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["RGB", "D", "ED", "RGB+ED"])
def test_forward_parity_float32(mode):
    params = random_scene(80, seed=1, dtype=torch.float32)
    viewmats, Ks = cameras(torch.float32)
    bg = torch.rand(3, 3, generator=torch.Generator().manual_seed(5))
    (img, alpha, meta), (ref_img, ref_alpha, ref_meta) = both(params, viewmats, Ks, render_mode=mode, backgrounds=bg)
    assert img.shape == (3, H, W, {"RGB": 3, "D": 1, "ED": 1, "RGB+ED": 4}[mode])
    assert alpha.shape == (3, H, W, 1)
    assert torch.equal(meta["radii"], ref_meta["radii"])
    assert meta["n_pairs"] > 1000 and (alpha > 0.5).float().mean() > 0.3  # a scene with real overlap
    assert (alpha - ref_alpha).abs().max() <= 1e-5
    if "RGB" in mode:
        assert (img[..., :3] - ref_img[..., :3]).abs().max() <= 1e-5
    if mode != "RGB":  # depth (2-6 units) to a relative 1e-5; expected depth D / alpha where alpha > 0.05
        # (below that, float32's 1 - T carries a relative error of ~1e-7 / alpha in either renderer)
        seen = alpha[..., 0] > (0.05 if "ED" in mode else -1.0)
        rel = ((img[..., -1] - ref_img[..., -1]).abs() / ref_img[..., -1].abs().clamp(min=1.0))[seen]
        assert seen.sum() > 500 and rel.max() <= 1e-5


@pytest.mark.parametrize(
    "kw",
    [
        {"sh_degree": 3, "render_mode": "RGB+D"},
        {"sh_degree": 1, "rasterize_mode": "antialiased"},
        {"per_camera_features": 5, "tile_size": 8},
        {"eps2d": 0.0, "near_plane": 2.2, "far_plane": 3.8, "radius_clip": 1.0},
    ],
)
def test_forward_parity_options_float64(kw):
    kw = dict(kw)
    features = kw.pop("per_camera_features", None)
    params = list(random_scene(60, seed=2, sh_degree=kw.get("sh_degree")))
    viewmats, Ks = cameras()
    if features:
        params[4] = torch.rand(len(viewmats), 60, features, dtype=torch.float64)
    (img, alpha, meta), (ref_img, ref_alpha, ref_meta) = both(params, viewmats, Ks, **kw)
    assert torch.equal(meta["radii"], ref_meta["radii"])
    assert torch.allclose(img, ref_img, rtol=0, atol=1e-10)
    assert torch.allclose(alpha, ref_alpha, rtol=0, atol=1e-10)


def test_gradient_parity_all_inputs():
    means, quats, scales, opacities, coeffs = random_scene(40, seed=3, sh_degree=2)
    viewmats, Ks = cameras(n=2)
    bg = torch.rand(2, 3, dtype=torch.float64)
    weights = torch.rand(2, H, W, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    grads = []
    for fn in (rasterization, rasterize_reference):
        inputs = [t.clone().requires_grad_() for t in (means, quats, scales, opacities, coeffs, bg)]
        img, alpha, _ = fn(*inputs[:5], viewmats, Ks, W, H, sh_degree=2, render_mode="RGB+ED", backgrounds=inputs[5])
        ((img * weights).sum() + (alpha * weights[..., :1]).sum()).backward()
        grads.append([t.grad for t in inputs])
    for name, g_fast, g_ref in zip(("means", "quats", "scales", "opacities", "sh", "bg"), *grads):
        assert torch.isfinite(g_fast).all(), name
        assert g_fast.abs().sum() > 0, name
        assert torch.allclose(g_fast, g_ref, rtol=1e-7, atol=1e-9), (name, (g_fast - g_ref).abs().max())


def test_gradcheck_float64():
    g = torch.Generator().manual_seed(7)
    means = torch.tensor([[0.05, 0.02, 3.0], [-0.3, 0.1, 3.5], [0.2, -0.15, 2.6]], dtype=torch.float64)
    quats = torch.randn(3, 4, generator=g, dtype=torch.float64)
    scales = torch.tensor([[0.12, 0.08, 0.1], [0.2, 0.1, 0.15], [0.06, 0.1, 0.08]], dtype=torch.float64)
    opacities = torch.tensor([0.7, 0.5, 0.6], dtype=torch.float64)
    colors = torch.rand(3, 3, generator=g, dtype=torch.float64)
    viewmats, Ks = cameras(n=1, width=12, height=10)

    def render(*inputs):
        img, alpha, _ = rasterization(*inputs, viewmats, Ks, 12, 10, render_mode="RGB+D")
        return torch.cat([img, alpha], dim=-1)

    inputs = tuple(t.requires_grad_() for t in (means, quats, scales, opacities, colors))
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


# --------------------------------------------------------------------------------------------------
# Edge cases and known answers
# --------------------------------------------------------------------------------------------------
def one_gaussian(mean, sigma=0.1, opacity=0.8, dtype=torch.float64):
    return (
        torch.tensor([mean], dtype=dtype),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype),
        torch.full((1, 3), sigma, dtype=dtype),
        torch.tensor([opacity], dtype=dtype),
        torch.tensor([[0.9, 0.2, 0.4]], dtype=dtype),
    )


@pytest.mark.parametrize(
    "mean, opacity",
    [
        ((0.0, 0.0, -2.0), 0.8),
        ((0.0, 0.0, 0.0), 0.8),
        ((0.0, 0.0, 1e11), 0.8),
        ((40.0, 0.0, 2.0), 0.8),
        ((0.0, 0.0, 3.0), 0.0),
        ((0.0, 0.0, 3.0), 0.003),
    ],
    ids=["behind", "at-camera", "beyond-far", "off-screen", "zero-opacity", "below-1/255"],
)
def test_invisible_gaussian_gives_background(mean, opacity):
    params = [t.requires_grad_() for t in one_gaussian(mean, opacity=opacity)]
    viewmats, Ks = cameras(n=1)
    bg = torch.tensor([[0.1, 0.5, 0.9]], dtype=torch.float64)
    img, alpha, meta = rasterization(*params, viewmats, Ks, W, H, backgrounds=bg, render_mode="RGB+ED")
    assert torch.equal(img[..., :3], bg.expand(1, H, W, 3).reshape(1, H, W, 3))
    assert torch.equal(img[..., 3], torch.zeros(1, H, W, dtype=torch.float64))
    assert torch.equal(alpha, torch.zeros(1, H, W, 1, dtype=torch.float64))
    assert meta["n_pairs"] == 0
    img.sum().backward()
    for t in params:
        assert torch.isfinite(t.grad).all() and not t.grad.any()


def test_empty_scene_gives_background():
    viewmats, Ks = cameras(n=2)
    empty = (torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3))
    bg = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    img, alpha, meta = rasterization(*empty, viewmats.float(), Ks.float(), W, H, backgrounds=bg)
    assert img.shape == (2, H, W, 3) and torch.equal(img, bg[:, None, None, :].expand(2, H, W, 3))
    assert not alpha.any() and meta["radii"].shape == (2, 0)
    img, alpha, _ = rasterization(*empty, viewmats.float(), Ks.float(), W, H)  # no background: black
    assert not img.any()


def test_isotropic_gaussian_facing_the_camera():
    """Centre pixel colour/alpha and the 2D std f*sigma/z (plus the 0.3 px^2 dilation)."""
    size, f, z, sigma, opacity = 33, 40.0, 4.0, 0.25, 0.8
    params = one_gaussian((0.0, 0.0, z), sigma=sigma, opacity=opacity)
    viewmats = torch.eye(4, dtype=torch.float64)[None]
    Ks = torch.tensor([[[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    bg = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    img, alpha, meta = rasterization(*params, viewmats, Ks, size, size, backgrounds=bg, render_mode="RGB+ED")
    c = size // 2  # pixel centre (c + 0.5) = size / 2: the projected mean
    assert meta["means2d"][0, 0].tolist() == [size / 2, size / 2]
    assert alpha[0, c, c, 0].item() == pytest.approx(opacity, abs=1e-12)
    expected = opacity * params[4][0] + (1 - opacity) * bg[0]
    assert torch.allclose(img[0, c, c, :3], expected, atol=1e-12)
    assert img[0, c, c, 3].item() == pytest.approx(z, abs=1e-12)  # expected depth of one Gaussian: its z
    # the alpha profile along the row through the centre: o * exp(-d^2 / (2 s^2)), s^2 = (f sigma / z)^2 + 0.3
    d = torch.arange(-4, 5, dtype=torch.float64)
    profile = alpha[0, c, c - 4 : c + 5, 0]
    s2_fit = -(d[d != 0] ** 2) / (2 * torch.log(profile[d != 0] / opacity))
    s_expected = math.sqrt((f * sigma / z) ** 2 + 0.3)
    assert torch.allclose(s2_fit.sqrt(), torch.full_like(s2_fit, s_expected), rtol=1e-9)
    assert s_expected == pytest.approx(f * sigma / z, rel=0.03)  # ~ f sigma / z = 2.5 px
    assert meta["radii"][0, 0].item() == math.ceil(3 * math.sqrt(s_expected**2 + 0.1))


def test_projection_matches_navcrafter_cameras():
    """viewmats are inverse navcrafter poses; means2d equal ``cameras.project`` (OpenCV, centres at +0.5)."""
    means, *_ = random_scene(20, seed=4)
    viewmats, Ks = cameras()
    poses = [np.linalg.inv(v) for v in viewmats.numpy()]
    _, _, meta = rasterization(*random_scene(20, seed=4), viewmats, Ks, W, H)
    for c, pose in enumerate(poses):
        uv, depth = project(means.numpy(), pose, Ks[c].numpy())
        ok = meta["radii"][c].numpy() > 0
        assert ok.sum() > 5
        assert np.allclose(meta["means2d"][c].numpy()[ok], uv[ok], atol=1e-9)
        assert np.allclose(meta["depths"][c].numpy()[ok], depth[ok], atol=1e-12)


@pytest.mark.parametrize("renderer", ["torch", "cpu"])
def test_transmittance_early_stop_is_exclusive(renderer):
    """Four opaque layers (o = 0.95): T = 0.05, 0.0025, 1.25e-4 and then 6.25e-6 <= 1e-4, so the fourth
    layer is skipped and the pixel keeps T = 1.25e-4; the same in the PyTorch renderer and the compiled kernels."""
    from navcrafter.models.gaussians.cpu_rasterize import rasterization as cpu_rasterization

    render = rasterization if renderer == "torch" else cpu_rasterization
    means = torch.tensor([[0.0, 0.0, z] for z in (2.0, 2.5, 3.0, 3.5)], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 4, dtype=torch.float64)
    scales = torch.full((4, 3), 0.05, dtype=torch.float64)
    opacities = torch.full((4,), 0.95, dtype=torch.float64)
    colors = torch.eye(4, 3, dtype=torch.float64) + torch.tensor([0, 0, 0, 1.0], dtype=torch.float64)[:, None]
    viewmats = torch.eye(4, dtype=torch.float64)[None]
    Ks = torch.tensor([[[20.0, 0, 8.5], [0, 20.0, 8.5], [0, 0, 1]]], dtype=torch.float64)
    img, alpha, _ = render(means, quats, scales, opacities, colors, viewmats, Ks, 16, 16)
    expected = 0.95 * colors[0] + 0.05 * 0.95 * colors[1] + 0.0025 * 0.95 * colors[2]
    assert torch.allclose(img[0, 8, 8], expected, atol=1e-12)  # pixel (8, 8): centre (8.5, 8.5) = the means
    assert alpha[0, 8, 8, 0].item() == pytest.approx(1 - 1.25e-4, abs=1e-12)
    ref, ref_alpha, _ = rasterize_reference(means, quats, scales, opacities, colors, viewmats, Ks, 16, 16)
    assert torch.allclose(img, ref, atol=1e-12) and torch.allclose(alpha, ref_alpha, atol=1e-12)


def test_cameras_batched_equal_separate():
    params = random_scene(50, seed=6, dtype=torch.float32)
    viewmats, Ks = cameras(torch.float32)
    img, alpha, _ = rasterization(*params, viewmats, Ks, W, H, render_mode="RGB+D")
    for c in range(3):
        one, one_alpha, _ = rasterization(*params, viewmats[c : c + 1], Ks[c : c + 1], W, H, render_mode="RGB+D")
        assert torch.allclose(one, img[c : c + 1], atol=2e-6) and torch.allclose(one_alpha, alpha[c : c + 1], atol=1e-6)


def test_bad_inputs_are_rejected():
    params = random_scene(5)
    viewmats, Ks = cameras(n=1)
    with pytest.raises(ValueError, match="render_mode"):
        rasterization(*params, viewmats, Ks, W, H, render_mode="RGBD")
    with pytest.raises(ValueError, match="opacities"):
        rasterization(*params[:3], params[3][:, None], params[4], viewmats, Ks, W, H)
    with pytest.raises(ValueError, match="SH coefficients"):
        rasterization(*params, viewmats, Ks, W, H, sh_degree=1)


# --------------------------------------------------------------------------------------------------
# Spherical harmonics
# --------------------------------------------------------------------------------------------------
def test_sh_basis_is_orthonormal_with_3dgs_signs():
    n = 40_000  # Fibonacci sphere quadrature
    i = torch.arange(n, dtype=torch.float64) + 0.5
    zc = 1 - 2 * i / n
    phi = math.pi * (3 - math.sqrt(5)) * i
    dirs = torch.stack([torch.sqrt(1 - zc**2) * torch.cos(phi), torch.sqrt(1 - zc**2) * torch.sin(phi), zc], -1)
    basis = sh_basis(3, dirs)
    gram = basis.T @ basis * (4 * math.pi / n)
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=2e-3)
    up = sh_basis(3, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))[0]
    nonzero = {0: SH_C0, 2: SH_C1, 6: 2 * SH_C2[2], 12: 2 * SH_C3[3]}
    assert torch.allclose(up, torch.tensor([nonzero.get(k, 0.0) for k in range(16)], dtype=torch.float64))
    x = sh_basis(1, torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64))[0]
    assert x.tolist() == [SH_C0, 0.0, 0.0, -SH_C1]  # 3DGS: -C1 x for the 4th basis


def test_sh_to_rgb_offset_clamp_and_partial_degree():
    coeffs = torch.randn(10, 16, 3, dtype=torch.float64)
    dirs = torch.randn(10, 3, dtype=torch.float64) * 5  # normalised inside
    rgb0 = sh_to_rgb(0, dirs, coeffs)
    assert torch.allclose(rgb0, torch.clamp_min(sh_dc_to_rgb(coeffs[:, 0]), 0.0))
    assert torch.equal(sh_to_rgb(1, dirs, coeffs), sh_to_rgb(1, dirs, coeffs[:, :4]))
    assert (sh_to_rgb(3, dirs, coeffs * 10) >= 0).all()


# --------------------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------------------
def test_model_from_point_cloud():
    pts = np.array([[0, 0, 3], [1, 0, 3], [0, 1, 3], [1, 1, 3], [5, 5, 3], [5, 5, 3]], dtype=np.float64)
    cols = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [128, 128, 128], [10, 20, 30], [10, 20, 30]], np.uint8)
    m = GaussianModel.from_point_cloud(pts, cols, sh_degree=2)
    assert len(m) == 6 and m.sh_degree == 2 and m.sh_rest.shape == (6, 8, 3) and not m.sh_rest.any()
    assert torch.allclose(m.opacities, torch.full((6,), 0.1))
    assert torch.equal(m.quats, torch.tensor([[1.0, 0, 0, 0]] * 6))
    # corner of the unit square: neighbours at 1, 1, sqrt(2) -> rms sqrt(4/3)
    assert torch.allclose(m.scales[0], torch.full((3,), math.sqrt(4 / 3)), rtol=1e-6)
    assert torch.isfinite(m.log_scales).all()  # duplicates: floor of 1e-7 on the mean squared distance
    assert torch.allclose(sh_dc_to_rgb(m.sh_dc), torch.tensor(cols / 255.0, dtype=torch.float32), atol=1e-6)
    single = GaussianModel.from_point_cloud(pts[:1], cols[:1] / 255.0, sh_degree=0, fallback_scale=0.02)
    assert single.sh_rest.shape == (1, 0, 3) and torch.allclose(single.scales, torch.full((1, 3), 0.02))
    with pytest.raises(ValueError):
        GaussianModel.from_point_cloud(pts, cols[:3])


def test_model_render_gradients_reach_raw_parameters():
    pts = np.random.default_rng(0).uniform([-1, -0.6, 2.5], [1, 0.6, 3.5], size=(40, 3))
    m = GaussianModel.from_point_cloud(pts, np.full((40, 3), 200, np.uint8), sh_degree=1).requires_grad_()
    viewmats, Ks = cameras(torch.float32, n=1)
    img, alpha, _ = m.render(viewmats, Ks, W, H, render_mode="RGB+ED")
    assert alpha.max() > 0.1
    (img.sum() + alpha.sum()).backward()
    for name, t in m.tensors().items():
        assert t.grad is not None and torch.isfinite(t.grad).all(), name
        assert t.grad.abs().sum() > 0 or name == "quats", name  # isotropic: rotation has no effect


# --------------------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------------------
def _random_model(n=30, degree=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return GaussianModel(
        means=torch.rand(n, 3, generator=g) * torch.tensor([2.0, 1.2, 1.0]) + torch.tensor([-1.0, -0.6, 2.5]),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.rand(n, 3, generator=g) - 3.5,
        opacity_logits=torch.randn(n, generator=g),
        sh_dc=torch.randn(n, 3, generator=g),
        sh_rest=torch.randn(n, k - 1, 3, generator=g) * 0.3,
    )


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_ply_round_trip_is_bit_exact(tmp_path, degree):
    model = _random_model(degree=degree)
    path = save_ply(tmp_path / "splat.ply", model, comments="SIMULATION MODE: test label\nsecond line")
    loaded = load_ply(path)
    for name, t in model.tensors().items():
        other = loaded.tensors()[name]
        assert other.dtype == torch.float32 and other.shape == t.shape, name
        assert torch.equal(t.view(torch.int32), other.view(torch.int32)), name  # bit for bit
    viewmats, Ks = cameras(torch.float32, n=2)
    a = model.render(viewmats, Ks, W, H, render_mode="RGB+ED")
    b = loaded.render(viewmats, Ks, W, H, render_mode="RGB+ED")
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    header = read_ply_header(path)
    assert header.comments == ("SIMULATION MODE: test label", "second line")
    n_props = 3 + 3 + 3 + 3 * ((degree + 1) ** 2 - 1) + 1 + 3 + 4
    assert list(header.vertex_dtype.names) == property_names(degree) and len(property_names(degree)) == n_props
    assert path.stat().st_size == header.data_offset + len(model) * n_props * 4


def test_ply_layout_matches_3dgs(tmp_path):
    model = _random_model(n=2, degree=3)
    arr = to_structured(model)
    # f_rest is channel-major: f_rest_{c * 15 + k} = coefficient k + 1 of channel c
    for c in range(3):
        for k in range(15):
            assert arr[f"f_rest_{c * 15 + k}"][1] == model.sh_rest[1, k, c].item()
    assert arr["rot_0"][0] == model.quats[0, 0].item() and arr["opacity"][1] == model.opacity_logits[1].item()
    assert arr["scale_2"][0] == model.log_scales[0, 2].item() and arr["nx"][0] == 0.0
    raw = save_ply(tmp_path / "a.ply", model).read_bytes()
    assert raw.startswith(b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n")
    assert b"property float f_rest_44\nproperty float opacity\n" in raw and b"end_header\n" in raw


def test_ply_rejects_other_files(tmp_path):
    xyz = tmp_path / "cloud.ply"
    xyz.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n" + np.zeros(3, "<f4").tobytes()
    )
    with pytest.raises(ValueError, match="not a 3DGS PLY"):
        load_ply(xyz)
    ascii_ply = tmp_path / "ascii.ply"
    ascii_ply.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nend_header\n")
    with pytest.raises(ValueError, match="binary_little_endian"):
        load_ply(ascii_ply)


# --------------------------------------------------------------------------------------------------
# DropGaussian
# --------------------------------------------------------------------------------------------------
def test_drop_rate_schedule():
    assert drop_rate(0, 100, 0.2) == 0.0 and drop_rate(50, 100, 0.2) == pytest.approx(0.1)
    assert drop_rate(100, 100, 0.2) == pytest.approx(0.2) and drop_rate(500, 100, 0.2) == pytest.approx(0.2)
    with pytest.raises(ValueError):
        drop_rate(1, 100, 1.0)


def test_drop_gaussians_identity_when_not_training_or_zero_rate():
    o = torch.rand(100)
    assert drop_gaussians(o, 0.3, training=False) is o
    assert drop_gaussians(o, 0.0) is o
    dropper = DropGaussian(gamma=0.5, total_steps=10, seed=1)
    assert dropper(o, step=0) is o and dropper(o, step=7, training=False) is o


def test_drop_gaussians_preserves_opacity_in_expectation():
    o = torch.rand(2000, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    g = torch.Generator().manual_seed(3)
    draws = torch.stack([drop_gaussians(o, 0.3, generator=g) for _ in range(400)])
    kept = draws != 0
    assert kept.double().mean().item() == pytest.approx(0.7, abs=0.005)
    assert torch.allclose(draws[kept], (o.expand_as(draws) / 0.7)[kept])  # survivors scaled by 1/(1-r)
    assert (draws.mean(0) - o).abs().mean() < 0.02 and abs(draws.mean() - o.mean()) < 0.003


def test_drop_gaussian_is_seeded_and_gradients_reach_survivors_only():
    o = torch.rand(50).requires_grad_()
    a, b = DropGaussian(0.4, 10, seed=9), DropGaussian(0.4, 10, seed=9)
    assert torch.equal(a(o, step=10), b(o, step=10)) and torch.equal(a(o, step=5), b(o, step=5))
    out = DropGaussian(0.4, 10, seed=2)(o, step=10)
    out.sum().backward()
    assert torch.equal(o.grad, (out != 0).float() / 0.6)
