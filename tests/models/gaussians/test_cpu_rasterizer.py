"""The compiled CPU rasterizer (``models/gaussians/cpu_rasterize.py`` on ``cpu_kernels.py``): parity with the
PyTorch renderer (``rasterize.py``) in values and gradients, with the brute-force reference, ``gradcheck``,
edge cases, determinism across runs and thread counts, and the backend dispatch.

The scenes and cameras are test_gaussians.py's (imported from that module: its folder is on sys.path). The
first call compiles the kernels (numba caches them next to the module, later sessions load them).
"""

from __future__ import annotations

import concurrent.futures
import math

import numba
import numpy as np
import pytest
import torch
from test_gaussians import H, W, cameras, one_gaussian, random_scene  # the module pytest imported

from navcrafter.models.gaussians import cpu_rasterize
from navcrafter.models.gaussians.cpu_rasterize import rasterization as cpu_rasterization
from navcrafter.models.gaussians.rasterize import normalize_depth, quat_scale_to_covar, render_gaussians
from navcrafter.models.gaussians.rasterize import project_gaussians as torch_project
from navcrafter.models.gaussians.rasterize import rasterization as torch_rasterization
from navcrafter.models.gaussians.rasterize import rasterize_to_pixels as torch_rasterize_to_pixels
from navcrafter.models.gaussians.reference import rasterize_reference
from navcrafter.models.gaussians.renderer import rasterize, resolve_backend
from navcrafter.models.gaussians.sh import sh_to_rgb

pytestmark = pytest.mark.usefixtures("one_torch_thread")

CHANNELS = {"RGB": 3, "D": 1, "ED": 1, "RGB+D": 4, "RGB+ED": 4}


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest difference relative to the largest magnitude of ``b`` (at least 1e-30)."""
    return float((a - b).abs().max() / b.abs().max().clamp(min=1e-30)) if b.numel() else 0.0


def loss_weights(shape, seed=0, dtype=torch.float64):
    """Fixed weights, the same numbers in any dtype (drawn in float64)."""
    return torch.rand(shape, dtype=torch.float64, generator=torch.Generator().manual_seed(seed)).to(dtype)


def run_with_grads(fn, inputs: dict, viewmats, Ks, width=W, height=H, seed=0, retain_means2d=False, **kw):
    """Render with ``fn`` (leaf copies of ``inputs``), back-propagate a fixed weighting of image and alpha;
    returns (image, alpha, meta, {name: grad})."""
    leaves = {k: (None if v is None else v.detach().clone().requires_grad_()) for k, v in inputs.items()}
    bg = leaves.pop("backgrounds", None)
    if leaves.get("covars") is not None:
        kw["covars"] = leaves["covars"]
    img, alpha, meta = fn(leaves["means"], leaves.get("quats"), leaves.get("scales"), leaves["opacities"],
                          leaves["colors"], viewmats, Ks, width, height, backgrounds=bg, **kw)
    if retain_means2d:
        meta["means2d"].retain_grad()
    w = loss_weights(img.shape, seed, img.dtype)
    wa = loss_weights(alpha.shape, seed + 1, img.dtype)
    ((img * w).sum() + (alpha * wa).sum()).backward()
    grads = {k: v.grad for k, v in leaves.items() if v is not None}  # None: the input was not read
    if bg is not None:
        grads["backgrounds"] = bg.grad
    return img.detach(), alpha.detach(), meta, grads


def scene_inputs(n=60, seed=2, sh_degree=None, dtype=torch.float64, n_cam=3, backgrounds=True, covars=False):
    means, quats, scales, opacities, colors = random_scene(n, seed=seed, dtype=dtype, sh_degree=sh_degree)
    inputs = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors}
    if covars:
        inputs["covars"] = quat_scale_to_covar(quats, scales)
        inputs["quats"] = inputs["scales"] = None
    if backgrounds:
        inputs["backgrounds"] = torch.rand(n_cam, 3, dtype=dtype, generator=torch.Generator().manual_seed(seed + 9))
    return inputs


@pytest.fixture
def one_numba_thread():
    """One kernel thread, for tests that make hundreds of tiny calls: on a busy 2-core machine, with libgomp's
    default OMP_WAIT_POLICY, every parallel kernel launch on 2 threads costs ~8 ms (results do not depend on the
    thread count, test_deterministic_and_independent_of_the_thread_count)."""
    before = numba.get_num_threads()
    cpu_rasterize.set_threads(1)
    yield
    cpu_rasterize.set_threads(before)


def positional(inputs: dict) -> tuple:
    return tuple(inputs[k] for k in ("means", "quats", "scales", "opacities", "colors"))


# --------------------------------------------------------------------------------------------------
# Parity with the PyTorch renderer, float64
# --------------------------------------------------------------------------------------------------
FORWARD_CASES = [
    {"render_mode": "RGB"},
    {"render_mode": "D", "alpha_clamp": 0.999},
    {"render_mode": "ED", "rasterize_mode": "antialiased"},
    {"render_mode": "RGB+D", "sh_degree": 0, "bg": False},
    {"render_mode": "RGB+ED", "sh_degree": 1, "alpha_clamp": 0.999},
    {"render_mode": "RGB", "sh_degree": 2, "rasterize_mode": "antialiased", "bg": False},
    {"render_mode": "RGB+ED", "sh_degree": 3, "rasterize_mode": "antialiased", "alpha_clamp": 0.999},
    {"render_mode": "RGB+D", "sh_degree": 3, "bg": False, "alpha_clamp": 0.999},
    {"render_mode": "RGB", "per_camera_features": 5, "bg": False},
    {"render_mode": "RGB+D", "eps2d": 0.0, "near_plane": 2.2, "far_plane": 3.8, "radius_clip": 1.0},
]


@pytest.mark.parametrize("case", FORWARD_CASES, ids=lambda c: "-".join(f"{k}={v}" for k, v in c.items()))
def test_forward_parity_with_torch_float64(case):
    kw = dict(case)
    use_bg, feats = kw.pop("bg", True), kw.pop("per_camera_features", None)
    inputs = scene_inputs(80, seed=1, sh_degree=kw.get("sh_degree"), backgrounds=use_bg)
    viewmats, Ks = cameras()
    if feats:
        inputs["colors"] = torch.rand(3, 80, feats, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    bg = inputs.get("backgrounds")
    img, alpha, meta = cpu_rasterization(*positional(inputs), viewmats, Ks, W, H, backgrounds=bg, **kw)
    ref, ref_alpha, ref_meta = torch_rasterization(*positional(inputs), viewmats, Ks, W, H, backgrounds=bg, **kw)
    n_ch = feats or CHANNELS[kw["render_mode"]]
    assert img.shape == ref.shape == (3, H, W, n_ch) and alpha.shape == (3, H, W, 1)
    assert img.dtype == alpha.dtype == torch.float64
    assert (ref_alpha > 0.5).double().mean() > 0.2 and ref_meta["n_pairs"] > 1000  # a scene with real overlap
    assert rel_err(img, ref) <= 1e-9 and (alpha - ref_alpha).abs().max() <= 1e-9
    radii = meta["radii"]
    assert radii.dtype == torch.int32 and torch.equal(radii, ref_meta["radii"])
    assert (radii == 0).any() and (radii > 0).sum() > 100
    vis = radii > 0
    assert (meta["means2d"] - ref_meta["means2d"])[vis].abs().max() <= 1e-9
    assert (meta["conics"] - ref_meta["conics"])[vis].abs().max() <= 1e-9 * ref_meta["conics"][vis].abs().max()
    assert torch.allclose(meta["depths"], ref_meta["depths"], rtol=0, atol=1e-12)
    assert torch.allclose(meta["opacities"], ref_meta["opacities"], rtol=0, atol=1e-12)
    assert meta["n_isects"] == ref_meta["n_isects"]
    assert torch.equal(meta["tiles_per_gauss"], ref_meta["tiles_per_gauss"])
    assert (meta["tile_width"], meta["tile_height"]) == (ref_meta["tile_width"], ref_meta["tile_height"])
    if use_bg and "RGB" in kw["render_mode"]:  # uncovered pixels show the background
        t = 1.0 - alpha[..., 0]
        assert torch.allclose(img[..., :3][t == 1], bg[:, None, None, :].expand(3, H, W, 3)[t == 1])


GRAD_CASES = [
    {"sh_degree": 2, "render_mode": "RGB+ED", "rasterize_mode": "antialiased"},
    {"render_mode": "RGB+D", "alpha_clamp": 0.999},
    {"sh_degree": 3, "render_mode": "RGB", "covars": True},
    {"sh_degree": 0, "render_mode": "ED", "covars": True, "rasterize_mode": "antialiased", "bg": False},
    {"render_mode": "D", "bg": False},
    {"render_mode": "RGB+ED", "per_camera_features": 4, "bg": False, "tile_size": 8},
]


@pytest.mark.parametrize("case", GRAD_CASES, ids=lambda c: "-".join(f"{k}={v}" for k, v in c.items()))
def test_gradient_parity_with_torch_float64(case):
    kw = dict(case)
    use_bg, use_covars, feats = kw.pop("bg", True), kw.pop("covars", False), kw.pop("per_camera_features", None)
    inputs = scene_inputs(50, seed=3, sh_degree=kw.get("sh_degree"), n_cam=2, backgrounds=use_bg, covars=use_covars)
    if feats:  # [C, N, D] features
        inputs["colors"] = torch.rand(2, 50, feats, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    viewmats, Ks = cameras(n=2)
    img, alpha, _, grads = run_with_grads(cpu_rasterization, inputs, viewmats, Ks, **kw)
    ref, ref_alpha, _, ref_grads = run_with_grads(torch_rasterization, inputs, viewmats, Ks, **kw)
    assert rel_err(img, ref) <= 1e-9 and (alpha - ref_alpha).abs().max() <= 1e-9
    assert grads.keys() == ref_grads.keys()
    depth_only = kw["render_mode"] in ("D", "ED")
    for name, g in grads.items():
        r = ref_grads[name]
        if depth_only and name == "colors":  # depth modes do not read colours
            assert g is None and r is None
            continue
        assert g is not None and g.shape == r.shape and torch.isfinite(g).all(), name
        assert r.abs().max() > 0, name
        assert rel_err(g, r) <= 1e-9, (name, rel_err(g, r))


# --------------------------------------------------------------------------------------------------
# float32
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kw", [{"render_mode": "RGB+ED", "sh_degree": 3}, {"render_mode": "D"},
                                {"render_mode": "RGB", "rasterize_mode": "antialiased"}], ids=["RGB+ED-sh3", "D", "aa"])
def test_float32_matches_float64_torch(kw):
    """float32 inputs (the fit's dtype): colours, alpha and gradients within 1e-5 of the float64 PyTorch result on
    the same (float32-rounded) inputs; depth channels relative to their largest value."""
    inputs32 = scene_inputs(80, seed=4, sh_degree=kw.get("sh_degree"), dtype=torch.float32)
    inputs64 = {k: v.double() for k, v in inputs32.items()}
    vm32, K32 = cameras(torch.float32)
    img, alpha, meta, grads = run_with_grads(cpu_rasterization, inputs32, vm32, K32, **kw)
    ref, ref_alpha, _, ref_grads = run_with_grads(torch_rasterization, inputs64, vm32.double(), K32.double(), **kw)
    assert img.dtype == alpha.dtype == meta["means2d"].dtype == torch.float32
    assert (alpha.double() - ref_alpha).abs().max() <= 1e-5
    mode = kw["render_mode"]
    if "RGB" in mode:
        assert (img[..., :3].double() - ref[..., :3]).abs().max() <= 1e-5
    if mode != "RGB":
        assert rel_err(img[..., -1].double(), ref[..., -1]) <= 1e-5
    for name, g in grads.items():
        if mode == "D" and name in ("colors", "backgrounds"):  # not read in depth modes
            assert g is None and ref_grads[name] is None
            continue
        assert g.dtype == torch.float32 and ref_grads[name].abs().max() > 0, name
        assert rel_err(g.double(), ref_grads[name]) <= 1e-5, (name, rel_err(g.double(), ref_grads[name]))


# --------------------------------------------------------------------------------------------------
# Against the brute-force reference
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["RGB", "RGB+ED", "D"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_forward_matches_reference(mode, dtype):
    params = random_scene(80, seed=1, dtype=dtype, sh_degree=1)
    viewmats, Ks = cameras(dtype)
    bg = torch.rand(3, 3, generator=torch.Generator().manual_seed(5), dtype=dtype)
    kw = {"render_mode": mode, "backgrounds": bg, "sh_degree": 1}
    img, alpha, meta = cpu_rasterization(*params, viewmats, Ks, W, H, **kw)
    ref, ref_alpha, ref_meta = rasterize_reference(*params, viewmats, Ks, W, H, **kw)
    assert torch.equal(meta["radii"], ref_meta["radii"])
    assert (alpha > 0.5).float().mean() > 0.3
    tol = 1e-5 if dtype == torch.float32 else 1e-10
    assert (alpha - ref_alpha).abs().max() <= tol
    if "RGB" in mode:
        assert (img[..., :3] - ref[..., :3]).abs().max() <= tol
    if mode != "RGB":  # depth (2-6 units) relative to 1, expected depth where alpha > 0.05 (see test_gaussians.py)
        seen = alpha[..., 0] > (0.05 if "ED" in mode else -1.0)
        rel = ((img[..., -1] - ref[..., -1]).abs() / ref[..., -1].abs().clamp(min=1.0))[seen]
        assert seen.sum() > 500 and rel.max() <= tol


def test_gradients_match_reference_float64():
    means, quats, scales, opacities, coeffs = random_scene(40, seed=3, sh_degree=2)
    inputs = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": coeffs,
              "backgrounds": torch.rand(2, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))}
    viewmats, Ks = cameras(n=2)
    kw = {"sh_degree": 2, "render_mode": "RGB+ED"}
    _, _, _, grads = run_with_grads(cpu_rasterization, inputs, viewmats, Ks, **kw)
    _, _, _, ref_grads = run_with_grads(rasterize_reference, inputs, viewmats, Ks, **kw)
    for name, g in grads.items():
        assert ref_grads[name].abs().max() > 0, name
        assert torch.allclose(g, ref_grads[name], rtol=1e-7, atol=1e-9), (name, (g - ref_grads[name]).abs().max())


def test_gradcheck_float64(one_numba_thread):
    g = torch.Generator().manual_seed(7)
    means = torch.tensor([[0.05, 0.02, 3.0], [-0.3, 0.1, 3.5], [0.2, -0.15, 2.6]], dtype=torch.float64)
    quats = torch.randn(3, 4, generator=g, dtype=torch.float64)
    scales = torch.tensor([[0.12, 0.08, 0.1], [0.2, 0.1, 0.15], [0.06, 0.1, 0.08]], dtype=torch.float64) * 3
    opacities = torch.tensor([0.7, 0.5, 0.6], dtype=torch.float64)
    colors = torch.rand(3, 3, generator=g, dtype=torch.float64)
    bg = torch.tensor([[0.2, 0.4, 0.9]], dtype=torch.float64)
    viewmats, Ks = cameras(n=1, width=12, height=10)

    def render(means, quats, scales, opacities, colors, bg):
        img, alpha, _ = cpu_rasterization(means, quats, scales, opacities, colors, viewmats, Ks, 12, 10,
                                          render_mode="RGB+ED", backgrounds=bg, rasterize_mode="antialiased")
        return torch.cat([img, alpha], dim=-1)

    inputs = tuple(t.requires_grad_() for t in (means, quats, scales, opacities, colors, bg))
    out = render(*inputs)
    assert out[..., 4].max() > 0.5  # the Gaussians are seen
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


# --------------------------------------------------------------------------------------------------
# Edge cases
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_empty_scene_gives_background(dtype):
    viewmats, Ks = cameras(dtype, n=2)
    empty = [torch.zeros(0, 3, dtype=dtype), torch.zeros(0, 4, dtype=dtype), torch.zeros(0, 3, dtype=dtype),
             torch.zeros(0, dtype=dtype), torch.zeros(0, 3, dtype=dtype)]
    empty = [t.requires_grad_() for t in empty]
    bg = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=dtype, requires_grad=True)
    img, alpha, meta = cpu_rasterization(*empty, viewmats, Ks, W, H, backgrounds=bg, render_mode="RGB+ED")
    assert img.shape == (2, H, W, 4) and torch.equal(img[..., :3], bg.detach()[:, None, None, :].expand(2, H, W, 3))
    assert not img[..., 3].any() and not alpha.any()
    assert meta["radii"].shape == (2, 0) and meta["n_isects"] == 0
    img.sum().backward()
    assert torch.equal(bg.grad, torch.full((2, 3), float(H * W), dtype=dtype))
    assert all(t.grad is not None and t.grad.shape == t.shape for t in empty)
    img, alpha, _ = cpu_rasterization(*[t.detach() for t in empty], viewmats, Ks, W, H)  # no background: black
    assert img.shape == (2, H, W, 3) and not img.any() and not alpha.any()


@pytest.mark.parametrize(
    "mean, opacity, culled",
    [
        ((0.0, 0.0, -2.0), 0.8, True),
        ((0.0, 0.0, 0.0), 0.8, True),
        ((0.0, 0.0, 1e11), 0.8, True),
        ((40.0, 0.0, 2.0), 0.8, True),
        ((0.0, 0.0, 3.0), 0.0, False),
        ((0.0, 0.0, 3.0), 0.003, False),
    ],
    ids=["behind", "at-camera", "beyond-far", "off-screen", "zero-opacity", "below-1/255"],
)
def test_invisible_gaussian_gives_background_and_no_gradient(mean, opacity, culled):
    params = [t.requires_grad_() for t in one_gaussian(mean, opacity=opacity)]
    viewmats, Ks = cameras(n=1)
    bg = torch.tensor([[0.1, 0.5, 0.9]], dtype=torch.float64)
    img, alpha, meta = cpu_rasterization(*params, viewmats, Ks, W, H, backgrounds=bg, render_mode="RGB+ED")
    assert torch.equal(img[..., :3], bg.expand(1, H, W, 3).reshape(1, H, W, 3))
    assert not img[..., 3].any() and not alpha.any()
    assert (meta["radii"][0, 0].item() == 0) == culled and (meta["n_isects"] == 0) == culled
    (img.sum() + alpha.sum()).backward()
    for t in params:
        assert torch.isfinite(t.grad).all() and not t.grad.any()


def test_culled_gaussians_in_a_scene_get_no_gradient():
    """random_scene's Gaussian 0 is behind every camera, 1 far off-screen: radii 0, zero gradients, while the
    others' gradients equal the PyTorch renderer's."""
    inputs = scene_inputs(40, seed=5, sh_degree=1)
    viewmats, Ks = cameras()
    kw = {"sh_degree": 1, "render_mode": "RGB+D"}
    _, _, meta, grads = run_with_grads(cpu_rasterization, inputs, viewmats, Ks, **kw)
    _, _, _, ref_grads = run_with_grads(torch_rasterization, inputs, viewmats, Ks, **kw)
    assert not meta["radii"][:, :2].any() and meta["radii"][:, 3:].any()
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert not grads[name][:2].any(), name
        assert grads[name][3:].abs().max() > 0, name
        assert rel_err(grads[name], ref_grads[name]) <= 1e-9, name


def test_gradient_of_the_backgrounds_alone_matches_torch():
    """Only the backgrounds want a gradient: the forward keeps no pairs, the backward still gives theirs."""
    inputs = scene_inputs(40, seed=4, n_cam=2)
    viewmats, Ks = cameras(n=2)
    grads = []
    for fn in (cpu_rasterization, torch_rasterization):
        bg = inputs["backgrounds"].clone().requires_grad_()
        img, alpha, _ = fn(*positional(inputs), viewmats, Ks, W, H, backgrounds=bg, render_mode="RGB+ED")
        ((img * loss_weights(img.shape)).sum() + alpha.sum()).backward()
        grads.append(bg.grad)
    assert grads[1].abs().min() > 0 and rel_err(grads[0], grads[1]) <= 1e-9


@pytest.mark.parametrize("n_cam", [1, 3])
@pytest.mark.parametrize("mode", ["RGB", "RGB+ED"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_features_skip_culled_gaussians_bit_for_bit(dtype, mode, n_cam):
    """The compiled SH features (``composite_features``: culled Gaussians' SH not evaluated, the depth column
    written beside the colours) give the renders and every gradient bit for bit as the compiled ``resolve_colors``
    (every colour evaluated) and PyTorch's concatenation, with Gaussians culled in some cameras and not others."""
    inputs = scene_inputs(60, seed=11, sh_degree=3, dtype=dtype, n_cam=n_cam)
    inputs["means"] = inputs["means"] * torch.tensor([2.5, 2.5, 1.0], dtype=dtype)  # many off-screen in some cameras
    viewmats, Ks = cameras(dtype=dtype, n=n_cam)

    def concatenated(means, colors, viewmats, sh_degree, radii, depths, with_depth):
        feats = cpu_rasterize.resolve_colors(means, colors, viewmats, sh_degree)
        return torch.cat([feats, depths[..., None]], dim=-1) if with_depth else feats

    def old_path(*args, **kw):
        return render_gaussians(cpu_rasterize.project_gaussians, cpu_rasterize.rasterize_to_pixels, *args,
                                features_fn=concatenated, project_qs=cpu_rasterize.project_gaussians_qs, **kw)

    kw = {"sh_degree": 3, "render_mode": mode, "near_plane": 0.01, "far_plane": 1e10, "radius_clip": 0.0,
          "eps2d": 0.3, "tile_size": 16, "rasterize_mode": "classic", "covars": None, "alpha_clamp": 0.99}
    img, alpha, meta, grads = run_with_grads(cpu_rasterization, inputs, viewmats, Ks, **kw)
    ref, ref_alpha, _, ref_grads = run_with_grads(old_path, inputs, viewmats, Ks, **kw)
    culled = meta["radii"] == 0
    assert culled.sum() >= 5 and (~culled).sum() >= 5
    assert n_cam == 1 or (culled.any(0) & ~culled.all(0)).any()  # culled in one camera, composited in another
    assert torch.equal(img, ref) and torch.equal(alpha, ref_alpha)
    assert grads.keys() == ref_grads.keys()
    for name, g in grads.items():
        assert ref_grads[name].abs().max() > 0, name
        assert torch.equal(g, ref_grads[name]), (name, rel_err(g, ref_grads[name]))


def test_many_stacked_opaque_gaussians_match_torch():
    """40 opaque Gaussians stacked along the axis (some at equal depths: ties keep index order): most pixels
    stop early, at different list positions; image and gradients equal the PyTorch renderer's."""
    g = torch.Generator().manual_seed(11)
    n = 40
    z = 2.0 + torch.arange(n, dtype=torch.float64) // 2 * 0.1  # pairs of equal depth
    means = torch.stack([torch.randn(n, generator=g, dtype=torch.float64) * 0.15,
                         torch.randn(n, generator=g, dtype=torch.float64) * 0.1, z], dim=-1)
    inputs = {"means": means, "quats": torch.randn(n, 4, generator=g, dtype=torch.float64),
              "scales": torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.4 + 0.1,
              "opacities": torch.rand(n, generator=g, dtype=torch.float64) * 0.1 + 0.9,
              "colors": torch.rand(n, 3, generator=g, dtype=torch.float64),
              "backgrounds": torch.tensor([[0.3, 0.6, 0.1]], dtype=torch.float64)}
    viewmats, Ks = cameras(n=1)
    img, alpha, _, grads = run_with_grads(cpu_rasterization, inputs, viewmats, Ks, render_mode="RGB+ED")
    ref, ref_alpha, _, ref_grads = run_with_grads(torch_rasterization, inputs, viewmats, Ks, render_mode="RGB+ED")
    assert (ref_alpha > 0.999).sum() > 100  # pixels that stopped (without the stop, T ~ 0.1^40 at the centre)
    assert rel_err(img, ref) <= 1e-9 and (alpha - ref_alpha).abs().max() <= 1e-12
    for name, gr in grads.items():
        assert rel_err(gr, ref_grads[name]) <= 1e-9, name
    # the stop is exclusive: no pixel's transmittance is at or below 1e-4
    assert (1 - alpha).min() > 1e-4


@pytest.mark.parametrize("width, height, tile_size", [(37, 23, 16), (W, H, 8), (37, 23, 8)])
def test_odd_sizes_and_tile_size_8_match_torch(width, height, tile_size):
    inputs = scene_inputs(60, seed=6, sh_degree=1, n_cam=2)
    viewmats, Ks = cameras(n=2, width=width, height=height)
    kw = {"sh_degree": 1, "render_mode": "RGB+ED", "tile_size": tile_size}
    img, alpha, meta, grads = run_with_grads(cpu_rasterization, inputs, viewmats, Ks, width, height, **kw)
    ref, ref_alpha, ref_meta, ref_grads = run_with_grads(torch_rasterization, inputs, viewmats, Ks, width, height,
                                                         **kw)
    assert img.shape == (2, height, width, 4) and (alpha > 0.5).double().mean() > 0.2
    assert meta["tile_width"] == math.ceil(width / tile_size) and meta["n_isects"] == ref_meta["n_isects"]
    assert torch.equal(meta["radii"], ref_meta["radii"])
    # the last row and column (partial tiles) are rendered too
    assert alpha[:, -1].max() > 0.1 and alpha[:, :, -1].max() > 0.1
    assert rel_err(img, ref) <= 1e-9 and (alpha - ref_alpha).abs().max() <= 1e-9
    for name, gr in grads.items():
        assert rel_err(gr, ref_grads[name]) <= 1e-9, name


# --------------------------------------------------------------------------------------------------
# Determinism, threads, means2d gradients
# --------------------------------------------------------------------------------------------------
def _bitwise_run():
    inputs = scene_inputs(300, seed=8, sh_degree=2, dtype=torch.float32)
    viewmats, Ks = cameras(torch.float32, width=64, height=48)
    img, alpha, meta, grads = run_with_grads(cpu_rasterization, inputs, viewmats, Ks, 64, 48, retain_means2d=True,
                                             sh_degree=2, render_mode="RGB+ED")
    return [img, alpha, meta["means2d"].grad, *grads.values()]


def _assert_bitwise_equal(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert x.dtype == y.dtype and torch.equal(x.view(torch.int32), y.view(torch.int32))


def test_deterministic_and_independent_of_the_thread_count():
    before = numba.get_num_threads()
    try:
        assert cpu_rasterize.set_threads(2) == min(2, numba.config.NUMBA_NUM_THREADS)
        first = _bitwise_run()
        _assert_bitwise_equal(first, _bitwise_run())
        assert cpu_rasterize.set_threads(1) == 1
        _assert_bitwise_equal(first, _bitwise_run())
        with pytest.raises(ValueError, match="threads"):
            cpu_rasterize.set_threads(0)
        assert cpu_rasterize.set_threads(None) == numba.config.NUMBA_NUM_THREADS
    finally:
        cpu_rasterize.set_threads(before)
    assert numba.get_num_threads() == before


def test_concurrent_calls_from_python_threads_give_the_same_bits():
    """The explore flow renders scenes on a thread pool: calls are serialised inside, results unchanged."""
    first = _bitwise_run()
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        runs = [f.result() for f in [pool.submit(_bitwise_run) for _ in range(3)]]
    for run in runs:
        _assert_bitwise_equal(first, run)


def test_means2d_retain_grad_equals_torch():
    inputs = scene_inputs(60, seed=9, sh_degree=1)
    viewmats, Ks = cameras()
    kw = {"sh_degree": 1, "render_mode": "RGB+D", "retain_means2d": True}
    _, _, meta, _ = run_with_grads(cpu_rasterization, inputs, viewmats, Ks, **kw)
    _, _, ref_meta, _ = run_with_grads(torch_rasterization, inputs, viewmats, Ks, **kw)
    g, r = meta["means2d"].grad, ref_meta["means2d"].grad
    assert g is not None and g.shape == (3, 60, 2) and r.abs().max() > 0
    assert rel_err(g, r) <= 1e-9
    assert not g[meta["radii"] == 0].any()  # culled Gaussians get none (densification counts the others)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_expected_depth_in_the_compositing_matches_torch(dtype):
    """``rasterize_to_pixels(..., expected_depth=True)``: the compiled kernels divide the last feature by the
    clamped alpha (forward) and take its gradient back (backward) bit for bit as PyTorch's ``normalize_depth`` on
    the kernels' accumulated depth does, and to rounding as the PyTorch renderer; the backgrounds' gradient too, in
    every column (through ``rasterization`` the depth column's background is a constant zero: only a direct call
    sees it)."""
    inputs = scene_inputs(60, seed=5, dtype=dtype, n_cam=2)
    viewmats, Ks = cameras(dtype=dtype, n=2)
    proj = torch_project(inputs["means"], quat_scale_to_covar(inputs["quats"], inputs["scales"]), viewmats, Ks, W, H)
    feats = torch.cat([torch.rand(2, 60, 3, dtype=dtype, generator=torch.Generator().manual_seed(6)),
                       proj["depths"][..., None]], dim=-1)
    bg = torch.rand(2, 4, dtype=dtype, generator=torch.Generator().manual_seed(7))
    leaves = (proj["means2d"], proj["conics"], feats, inputs["opacities"][None].expand(2, -1), bg)

    def run(fn, fused):
        xs = [x.detach().clone().requires_grad_() for x in leaves]
        img, alpha, _ = fn(*xs[:4], proj["radii"], proj["depths"], W, H, backgrounds=xs[4], expected_depth=fused)
        if not fused:
            img = normalize_depth(img, alpha)
        w, wa = loss_weights(img.shape, 0, dtype), loss_weights(alpha.shape, 1, dtype)
        ((img * w).sum() + (alpha * wa).sum()).backward()
        return (img.detach(), alpha.detach(), *(x.grad for x in xs))

    names = ("render", "alpha", "means2d", "conics", "features", "opacities", "backgrounds")
    ours = run(cpu_rasterize.rasterize_to_pixels, True)
    ref = run(torch_rasterize_to_pixels, True)
    assert (ref[1][..., 0] < 1e-3).any() and (ref[1][..., 0] > 0.5).any()  # empty and covered pixels
    for name, g, r in zip(names, ours, ref):
        assert g is not None and r.abs().max() > 0, name
        assert rel_err(g, r) <= (1e-9 if dtype == torch.float64 else 1e-4), (name, rel_err(g, r))
    for name, g, r in zip(names, ours, run(cpu_rasterize.rasterize_to_pixels, False)):
        assert torch.equal(g, r), (name, rel_err(g, r))


# --------------------------------------------------------------------------------------------------
# Refusals and dispatch
# --------------------------------------------------------------------------------------------------
def test_camera_gradients_are_refused():
    params = random_scene(10)
    viewmats, Ks = cameras(n=1)
    with pytest.raises(ValueError, match="backend='torch'"):
        cpu_rasterization(*params, viewmats.clone().requires_grad_(), Ks, W, H)
    with pytest.raises(ValueError, match="backend='torch'"):
        cpu_rasterization(*params, viewmats, Ks.clone().requires_grad_(), W, H)
    with pytest.raises(ValueError, match="backend='torch'"):
        rasterize(*params, viewmats.clone().requires_grad_(), Ks, W, H, backend="cpu")
    with pytest.raises(ValueError, match="render_mode"):  # the shared input checks apply
        cpu_rasterization(*params, viewmats, Ks, W, H, render_mode="RGBD")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_tensors_are_refused():
    params = [t.cuda() for t in random_scene(10)]
    viewmats, Ks = cameras(n=1)
    with pytest.raises(ValueError, match="CPU tensors"):
        cpu_rasterization(*params, viewmats.cuda(), Ks.cuda(), W, H)


def test_dispatch_auto_on_cpu_is_the_compiled_renderer():
    params = random_scene(60, seed=1, dtype=torch.float32, sh_degree=1)
    viewmats, Ks = cameras(torch.float32)
    img, alpha, meta = rasterize(*params, viewmats, Ks, W, H, sh_degree=1, render_mode="RGB+ED")
    assert meta["backend"] == "cpu" and resolve_backend("auto", "cpu") == "cpu"
    ref, ref_alpha, _ = cpu_rasterization(*params, viewmats, Ks, W, H, sh_degree=1, render_mode="RGB+ED")
    assert torch.equal(img, ref) and torch.equal(alpha, ref_alpha)  # alpha_clamp=None: ours, 0.99
    _, _, meta_t = rasterize(*params, viewmats, Ks, W, H, sh_degree=1, backend="torch")
    assert meta_t["backend"] == "torch"
    assert resolve_backend("cpu", "cpu") == "cpu"
    with pytest.raises(ValueError, match="CPU tensors"):
        resolve_backend("cpu", "cuda")
    with pytest.raises(ValueError, match="CPU tensors"):
        resolve_backend("cpu", "cuda:0")
    with pytest.raises(TypeError, match="absgrad"):
        rasterize(*params, viewmats, Ks, W, H, sh_degree=1, backend="cpu", absgrad=True)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_interleaved_graphs_do_not_share_work_arrays(dtype):
    """The kernels reuse work arrays between calls (``cpu_rasterize._Scratch``) only when nothing holds them:
    two graphs rendered before either backward pass (and a third render in between) give the gradients and
    images of renders made one at a time; results never share memory with a later call."""
    viewmats, Ks = cameras(dtype, n=2)
    a_in = scene_inputs(n=80, seed=3, dtype=dtype, n_cam=2, sh_degree=2)
    b_in = scene_inputs(n=50, seed=4, dtype=dtype, n_cam=2)
    alone = [run_with_grads(cpu_rasterization, x, viewmats, Ks, sh_degree=sh) for x, sh in ((a_in, 2), (b_in, None))]

    def start(inputs, sh):
        leaves = {k: v.detach().clone().requires_grad_() for k, v in inputs.items()}
        bg = leaves.pop("backgrounds")
        img, alpha, _ = cpu_rasterization(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                          leaves["colors"], viewmats, Ks, W, H, backgrounds=bg, sh_degree=sh)
        return leaves, img, alpha

    runs = [start(a_in, 2), start(b_in, None)]
    with torch.no_grad():
        start(b_in, None)
    for (leaves, img, alpha), ref in zip(runs, alone):
        w, wa = loss_weights(img.shape, 0, img.dtype), loss_weights(alpha.shape, 1, img.dtype)
        ((img * w).sum() + (alpha * wa).sum()).backward()
        assert torch.equal(img.detach(), ref[0]) and torch.equal(alpha.detach(), ref[1])
        for k, g in ref[3].items():
            if k != "backgrounds":
                assert torch.equal(leaves[k].grad, g), k


def test_kept_results_and_gradients_are_not_overwritten_by_later_calls():
    """Outputs and gradients live in reused buffers (``_Scratch``) only while nothing holds them: results kept
    from one render (image, alpha, meta, leaf gradients) keep their values and memory through later renders of
    another scene of the same sizes, and a later render's tensors never share memory with them."""
    viewmats, Ks = cameras(torch.float32, n=1)

    def render(seed):
        inputs = scene_inputs(n=60, seed=seed, dtype=torch.float32, sh_degree=3)
        leaves = {k: v.detach().clone().requires_grad_() for k, v in inputs.items() if k != "backgrounds"}
        img, alpha, meta = cpu_rasterization(leaves["means"], leaves["quats"], leaves["scales"],
                                             leaves["opacities"], leaves["colors"], viewmats, Ks, W, H, sh_degree=3,
                                             render_mode="RGB+ED")
        meta["means2d"].retain_grad()
        ((img * loss_weights(img.shape, 0, img.dtype)).sum() + alpha.sum()).backward()
        kept = [img, alpha, meta["means2d"], meta["depths"], meta["conics"], meta["radii"],
                meta["tiles_per_gauss"], meta["means2d"].grad] + [v.grad for v in leaves.values()]
        return [t.detach() for t in kept]

    first = render(5)
    copies = [t.clone() for t in first]
    later = render(6) + render(7)
    for t, c in zip(first, copies):
        assert torch.equal(t, c)
    ptrs = {t.untyped_storage().data_ptr() for t in first}
    assert not ptrs & {t.untyped_storage().data_ptr() for t in later}
    assert not torch.equal(first[0], later[0])  # another scene: the check above compares different values


@pytest.mark.parametrize("depths", ["float64", "float32", "ties", "one", "signs", "top bits"])
def test_bin_gaussians_sorts_each_tile_by_depth_stably(depths):
    """The binning's radix sort (digits over the bits in which the keys differ) against a stable argsort: the
    depth order of the visible Gaussians, each tile's list, and the entries' positions for the gradient gather;
    depths with all 64 bits differing, float32 values (low bits zero), ties (index order), one value, both signs,
    and keys differing only in their top bits."""

    from navcrafter.models.gaussians import cpu_kernels as K

    rng = np.random.default_rng(0)
    n_cam, n, tw, th = 2, 3000, 5, 4
    d = {"float64": rng.uniform(0.5, 9.0, (n_cam, n)),
         "float32": rng.uniform(0.5, 9.0, (n_cam, n)).astype(np.float32).astype(np.float64),
         "ties": rng.integers(0, 7, (n_cam, n)).astype(np.float64),
         "one": np.full((n_cam, n), 3.25),
         "signs": rng.uniform(-4.0, 4.0, (n_cam, n)),
         "top bits": np.where(rng.random((n_cam, n)) < 0.5, 2.0, -8.0) * 2.0 ** rng.integers(-3, 4, (n_cam, n)),
         }[depths]
    x0, y0 = rng.integers(0, tw, (n_cam, n)), rng.integers(0, th, (n_cam, n))
    x1, y1 = np.minimum(x0 + rng.integers(1, 3, (n_cam, n)), tw), np.minimum(y0 + rng.integers(1, 3, (n_cam, n)), th)
    cbox = (x0 | x1 << 16 | y0 << 32 | y1 << 48).astype(np.int64)
    cbox[rng.random((n_cam, n)) < 0.2] = 0  # not visible
    area = np.where(cbox != 0, (x1 - x0) * (y1 - y0), 0)
    n_ent = int(area.sum())
    offsets, gids, epos = np.empty(n_cam * tw * th + 1, np.int64), np.empty(n_ent, np.int64), np.empty(n_ent, np.int64)
    order, roff = np.empty((n_cam, n), np.int64), np.empty(n_cam * n + 1, np.int64)
    K.bin_gaussians(cbox, d.view(np.uint64), tw, th, offsets, gids, order, roff, epos, np.empty((4, n), np.int64),
                    np.empty((2, n), np.uint64), np.empty((64 // K.RADIX_BITS + 1, 1 << K.RADIX_BITS), np.int64))
    for c in range(n_cam):
        vis = np.flatnonzero(cbox[c] != 0)
        ranked = vis[np.argsort(d[c, vis], kind="stable")]
        assert np.array_equal(order[c, :len(vis)], ranked) and (order[c, len(vis):] == -1).all()
        for t in range(tw * th):
            ty, tx = divmod(t, tw)
            on = ranked[(x0[c, ranked] <= tx) & (tx < x1[c, ranked]) & (y0[c, ranked] <= ty) & (ty < y1[c, ranked])]
            lo, hi = offsets[c * tw * th + t], offsets[c * tw * th + t + 1]
            assert np.array_equal(gids[lo:hi], on)
        for r, g in enumerate(ranked):  # each entry of rank r: its list position holds g
            assert (gids[epos[roff[c * n + r]:roff[c * n + r + 1]]] == g).all()
            assert roff[c * n + r + 1] - roff[c * n + r] == area[c, g]


# --------------------------------------------------------------------------------------------------
# SH of a fit's two coefficient tensors (sh_dc, sh_rest) without their concatenation
# --------------------------------------------------------------------------------------------------
def _sh_grads(colors_fn, leaves: dict, dtype) -> tuple[torch.Tensor, dict]:
    rgb = colors_fn()
    (rgb * loss_weights(rgb.shape, 4, dtype)).sum().backward()
    return rgb.detach(), {k: v.grad for k, v in leaves.items()}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("n_cam", [1, 3])
def test_sh_colors_of_split_coefficients_equal_the_concatenated_bit_for_bit(degree, n_cam, dtype):
    """``sh_colors(means, sh_dc, sh_rest, ...)`` (the fit's path) gives the colours and gradients of
    ``resolve_colors`` on ``cat([sh_dc[:, None], sh_rest], 1)`` bit for bit in float32 (float64: to float64
    rounding; above the active degree: zero
    gradients, as the concatenation's); against PyTorch's SH to float rounding, with one channel's sum below the
    clamp (its gradient stopped) beside two above it."""
    means, _, _, _, coeffs = random_scene(40, seed=5, dtype=dtype, sh_degree=3)
    dc, rest = coeffs[:, 0].clone(), coeffs[:, 1:].clone()
    dc[3] = torch.tensor([1.0, -3.0, 0.5], dtype=dtype)  # channel 1 below the clamp at any degree:
    rest[3] = 0.0  # colour = C0 dc + 0.5
    viewmats, _ = cameras(dtype, n=n_cam)
    split = {"means": means.clone().requires_grad_(), "dc": dc.clone().requires_grad_(),
             "rest": rest.clone().requires_grad_()}
    rgb, g = _sh_grads(lambda: cpu_rasterize.sh_colors(split["means"], split["dc"], split["rest"], viewmats, degree),
                       split, dtype)
    cat = {"means": means.clone().requires_grad_(), "dc": dc.clone().requires_grad_(),
           "rest": rest.clone().requires_grad_()}
    rgb_cat, g_cat = _sh_grads(lambda: cpu_rasterize.resolve_colors(
        cat["means"], torch.cat([cat["dc"][:, None], cat["rest"]], 1), viewmats, degree), cat, dtype)
    # float32 (the fit's dtype): bit for bit. float64: the two layouts' kernels are compiled apart under fast-math,
    # and a fresh compile may reorder their sums differently (a fresh clone's CI run: degree-3 colours differed in
    # the last bits), so float64 rounding
    same = torch.equal if dtype == torch.float32 else (lambda a, b: rel_err(a, b) < 1e-14)
    assert rgb.shape == (n_cam, 40, 3) and same(rgb, rgb_cat)
    for k in split:
        assert g[k].is_contiguous(), k
        assert same(g[k], g_cat[k]), k
    assert not g["rest"][:, (degree + 1) ** 2 - 1:].any()
    ref = {"means": means.clone().requires_grad_(), "dc": dc.clone().requires_grad_(),
           "rest": rest.clone().requires_grad_()}
    rgb_ref, g_ref = _sh_grads(lambda: cpu_rasterize.torch_resolve_colors(
        ref["means"], torch.cat([ref["dc"][:, None], ref["rest"]], 1), viewmats, degree), ref, dtype)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert rel_err(rgb, rgb_ref) < tol and (rgb[:, 3, 1] == 0).all() and (rgb[:, 3, 0] > 0).all()
    for k in split:  # PyTorch's SH does not read the coefficients above the degree (no gradient: None)
        assert rel_err(g[k], torch.zeros_like(g[k]) if g_ref[k] is None else g_ref[k]) < tol, k
    assert (g["dc"][3, 0] != 0) and (g["dc"][3, 1] == 0)  # above the clamp: passes; below it: stopped


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("n_cam", [1, 3])
@pytest.mark.parametrize("n_coef", ["degree", 16])
def test_sh_kernels_on_coefficient_rows_match_pytorch_sh(degree, n_cam, n_coef):
    """The SH kernels on coefficient rows (``_coef_arrays``: one [N, K, 3] array as [N, 3 K] rows from column 3,
    or a fit's dc / rest pair from column 0; degree 3 runs straight-line code, the others loops): both layouts
    give the same bits, and sh.py's colours and gradients in float64 (1e-12); a Gaussian culled in a camera
    (radius 0; one culled in all) gets zeros there and adds no gradient from it, coefficients above the degree
    get zero gradients, the depth column is copied. Every output starts as NaN: each must be written."""
    means, _, _, _, coeffs = random_scene(50, seed=12, dtype=torch.float64, sh_degree=3)
    n, k = len(means), (degree + 1) ** 2 if n_coef == "degree" else 16
    co = coeffs[:, :k].contiguous()
    viewmats, _ = cameras(torch.float64, n=n_cam)
    campos = torch.linalg.inv(viewmats)[:, :3, 3]
    gen = torch.Generator().manual_seed(3)
    radii = (torch.rand(n_cam, n, generator=gen) > 0.3).to(torch.int32) * 2
    radii[:, 0] = 0
    depths = torch.rand(n_cam, n, generator=gen, dtype=torch.float64)
    v_rgb = torch.randn(n_cam, n, 4, generator=gen, dtype=torch.float64)
    outs = []
    for pair in (False, True):
        arrs = [co[:, 0].contiguous().numpy(), co[:, 1:].contiguous().numpy()] if pair else [co.numpy()]
        grads = [np.full_like(a, np.nan) for a in arrs]
        rgb, cut = np.full((n_cam, n, 4), np.nan), np.empty((n_cam, n), np.uint8)
        v_means = np.full((n, 3), np.nan)
        rows = cpu_rasterize._coef_arrays(arrs)
        m, cp, rad = means.numpy(), campos.numpy(), radii.numpy()
        cpu_rasterize.K.sh_forward(degree, m, cp, *rows, rad, depths.numpy(), rgb, cut)
        cpu_rasterize.K.sh_backward(degree, m, cp, *rows, rad, cut, v_rgb.numpy(), v_means,
                                    *cpu_rasterize._coef_arrays(grads)[:2])
        v_co = np.concatenate([grads[0][:, None], grads[1]], 1) if pair else grads[0]
        outs.append((rgb, cut, v_means, v_co))
    for a, b in zip(*outs):
        assert np.array_equal(a, b)
    rgb, _, v_means, v_co = (torch.from_numpy(a) for a in outs[0])
    vis = (radii > 0)[..., None]
    m, c = means.clone().requires_grad_(), co.clone().requires_grad_()
    ref = sh_to_rgb(degree, m[None] - campos[:, None], c[None].expand(n_cam, -1, -1, -1)) * vis
    (ref * v_rgb[..., :3]).sum().backward()
    assert torch.equal(rgb[..., 3], depths) and not rgb[:, 0, :3].any()
    assert rel_err(rgb[..., :3], ref.detach()) < 1e-12
    v_m_ref = torch.zeros_like(means) if m.grad is None else m.grad  # degree 0: no direction, no gradient
    assert rel_err(v_means, v_m_ref) < 1e-12 and rel_err(v_co, c.grad) < 1e-12
    assert not v_co[0].any() and not v_means[0].any() and not v_co[:, (degree + 1) ** 2:].any()


def test_sh_colors_refuses_mismatched_coefficients():
    means, _, _, _, coeffs = random_scene(10, sh_degree=1)
    viewmats, _ = cameras(n=1)
    with pytest.raises(ValueError, match="sh_dc must be"):
        cpu_rasterize.sh_colors(means, coeffs[:, :2, 0], coeffs[:, 1:], viewmats, 1)
    with pytest.raises(ValueError, match="K >= 9"):
        cpu_rasterize.sh_colors(means, coeffs[:, 0], coeffs[:, 1:], viewmats, 2)
