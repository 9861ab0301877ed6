"""The differentiable rasterizer: fast CPU path and tiled torch path against the dense
reference, gradients (gradcheck on the reference in float64), projection against the
pinhole model, edge cases, backend selection. No timing here (see bench-raster)."""
from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from engine.cameras import Intrinsics, View, c2w_gl_from_viewmat, project_points
from engine.raster import cpu as raster_cpu
from engine.raster import gsplat_backend, rasterization, resolve_backend
from engine.raster.projection import SH_C0, eval_colors, project_gaussians

NEEDS_NUMBA = pytest.mark.skipif(not raster_cpu.available(), reason="numba unavailable")


def look_viewmat(eye, target=(0.0, 0.0, 0.0)):
    """OpenCV world-to-camera matrix for a camera at eye looking at target (y-down image)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    f = target - eye
    f /= np.linalg.norm(f)
    up = np.array([0.0, -1.0, 0.0])
    r = np.cross(up, f)
    if np.linalg.norm(r) < 1e-9:
        r = np.array([1.0, 0.0, 0.0])
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    R = np.stack([r, d, f])  # rows: camera x (right), y (down), z (forward) in world
    vm = np.eye(4)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ eye
    return vm


def make_scene(N=60, W=37, H=29, C=1, seed=0, sh_degree=None, dtype=torch.float32,
               scale=0.08, spread=1.0):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(N, 3, generator=g, dtype=torch.float64) * 2 - 1) * spread
    quats = torch.randn(N, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(torch.randn(N, 3, generator=g, dtype=torch.float64) * 0.5) * scale
    opac = torch.sigmoid(torch.randn(N, generator=g, dtype=torch.float64) * 2)
    if sh_degree is None:
        colors = torch.rand(N, 3, generator=g, dtype=torch.float64)
    else:
        K = (sh_degree + 1) ** 2
        colors = torch.randn(N, K, 3, generator=g, dtype=torch.float64) * 0.3
    eyes = [(0.3 * c, -0.2 * c, -4.0 + 0.2 * c) for c in range(C)]
    viewmats = torch.tensor(np.stack([look_viewmat(e) for e in eyes]))
    f = 0.9 * W
    Ks = torch.tensor([[f, 0, W / 2 + 0.3], [0, f * 1.05, H / 2 - 0.2], [0, 0, 1]]).repeat(C, 1, 1)

    def to(t):
        return t.to(dtype)

    return dict(means=to(means), quats=to(quats), scales=to(scales), opacities=to(opac),
                colors=to(colors), viewmats=to(viewmats), Ks=to(Ks), width=W, height=H,
                sh_degree=sh_degree)


PARAMS = ("means", "quats", "scales", "opacities", "colors")


def render(scene, backend, grads=True, loss_weights=(1.0, 0.3, 0.1), **kw):
    """Render and (optionally) differentiate a fixed, non-trivial loss."""
    s = {k: (v.clone().requires_grad_(grads) if k in PARAMS else v) for k, v in scene.items()}
    args = [s[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks",
                           "width", "height")]
    colors, alphas, meta = rasterization(*args, sh_degree=s["sh_degree"], backend=backend, **kw)
    out = {"colors": colors, "alphas": alphas, "meta": meta}
    if grads:
        meta["means2d"].retain_grad()
        g = torch.Generator().manual_seed(123)
        wc = torch.rand(colors.shape, generator=g, dtype=colors.dtype).to(colors.device)
        loss = loss_weights[0] * (colors * wc).sum() + loss_weights[1] * (alphas * alphas).sum()
        if "depths" in meta:
            loss = loss + loss_weights[2] * meta["depths"].sum()
        loss.backward()
        out["grads"] = {k: s[k].grad for k in PARAMS}
        out["grads"]["means2d"] = meta["means2d"].grad
    return out


def assert_grads_close(ga, gb, rel=2e-3):
    for k in ga:
        a, b = ga[k], gb[k]
        assert a is not None and b is not None, k
        assert torch.isfinite(a).all() and torch.isfinite(b).all(), k
        scale = max(a.abs().max().item(), 1e-3)
        err = (a - b).abs().max().item()
        assert err <= rel * scale, f"{k}: max err {err:.3g} vs scale {scale:.3g}"


def assert_images_close(a, b, atol=2e-5, depth_atol=2e-4):
    torch.testing.assert_close(a["colors"], b["colors"], atol=atol, rtol=0)
    torch.testing.assert_close(a["alphas"], b["alphas"], atol=atol, rtol=0)
    if "depths" in a["meta"]:
        torch.testing.assert_close(a["meta"]["depths"], b["meta"]["depths"], atol=depth_atol, rtol=0)


# ---------------------------------------------------------------------------- projection

def test_means2d_match_pinhole_projection():
    sc = make_scene(N=20, C=2, dtype=torch.float64)
    proj = project_gaussians(sc["means"], sc["quats"], sc["scales"], sc["opacities"],
                             sc["viewmats"], sc["Ks"], sc["width"], sc["height"])
    for c in range(2):
        K = sc["Ks"][c].numpy()
        intr = Intrinsics(sc["width"], sc["height"], K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        view = View(intr, c2w_gl_from_viewmat(sc["viewmats"][c].numpy()))
        uv, z = project_points(view, sc["means"].numpy())
        np.testing.assert_allclose(proj.means2d[c].numpy(), uv, atol=1e-9)
        np.testing.assert_allclose(proj.z[c].numpy(), z, atol=1e-9)


def test_cov2d_is_jacobian_sandwich():
    """conic^-1 - eps2d = J Sigma_cam J^T, J = d(pixel)/d(camera point) by autograd."""
    sc = make_scene(N=5, dtype=torch.float64, spread=0.3)
    proj = project_gaussians(sc["means"], sc["quats"], sc["scales"], sc["opacities"],
                             sc["viewmats"], sc["Ks"], sc["width"], sc["height"], eps2d=0.3)
    K, vm = sc["Ks"][0], sc["viewmats"][0]
    q = sc["quats"] / sc["quats"].norm(dim=-1, keepdim=True)
    for n in range(5):
        w, x, y, z = q[n]
        Rq = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                           [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                           [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]],
                          dtype=torch.float64)
        S = Rq @ torch.diag(sc["scales"][n] ** 2) @ Rq.T
        pc = vm[:3, :3] @ sc["means"][n] + vm[:3, 3]
        J = torch.autograd.functional.jacobian(
            lambda p: torch.stack([K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2]]), pc)
        cov = J @ vm[:3, :3] @ S @ vm[:3, :3].T @ J.T + 0.3 * torch.eye(2, dtype=torch.float64)
        a, b, c = proj.conics[0, n]
        conic = torch.stack([torch.stack([a, b]), torch.stack([b, c])])
        torch.testing.assert_close(torch.linalg.inv(conic), cov, rtol=1e-9, atol=1e-9)
        # radius covers the 3.33-sigma (or opacity) extent on each axis
        ext = min(3.33, math.sqrt(2 * math.log(255 * float(sc["opacities"][n]))))
        assert proj.radii_xy[0, n, 0] == math.ceil(ext * math.sqrt(cov[0, 0]))
        assert proj.radii_xy[0, n, 1] == math.ceil(ext * math.sqrt(cov[1, 1]))


def test_sh_evaluation_convention():
    sc = make_scene(N=8, C=2, sh_degree=3, dtype=torch.float64)
    rgb = eval_colors(sc["means"], sc["colors"], sc["viewmats"], 3)
    assert rgb.shape == (2, 8, 3) and (rgb >= 0).all()
    assert not torch.allclose(rgb[0], rgb[1])  # view dependent
    rgb0 = eval_colors(sc["means"], sc["colors"][:, :1], sc["viewmats"], 0)
    torch.testing.assert_close(rgb0[0], torch.clamp_min(SH_C0 * sc["colors"][:, 0] + 0.5, 0))
    # degree 1 band: -C1*y*c1 + C1*z*c2 - C1*x*c3 with d the unit view direction
    cols = torch.zeros(8, 4, 3, dtype=torch.float64)
    cols[:, 3, 0] = 1.0
    rgb1 = eval_colors(sc["means"], cols, sc["viewmats"], 1)
    cam = -(sc["viewmats"][0, :3, :3].T @ sc["viewmats"][0, :3, 3])
    d = sc["means"] - cam
    d = d / d.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(rgb1[0, :, 0], torch.clamp_min(-0.4886025119029199 * d[:, 0] + 0.5, 0))


# ------------------------------------------------------------------- fast vs reference

@NEEDS_NUMBA
@pytest.mark.parametrize("seed,W,H,C", [(0, 37, 29, 1), (1, 40, 24, 2), (2, 17, 33, 3)])
def test_cpu_matches_reference(seed, W, H, C):
    sc = make_scene(N=80, W=W, H=H, C=C, seed=seed)
    ref, fast = render(sc, "reference"), render(sc, "cpu")
    assert fast["meta"]["backend"] == "cpu"
    assert_images_close(fast, ref)
    assert fast["alphas"].max() > 0.5  # the scene is not trivially empty
    torch.testing.assert_close(fast["meta"]["radii"], ref["meta"]["radii"])
    assert fast["meta"]["radii"].dtype == torch.int32
    assert_grads_close(fast["grads"], ref["grads"])


@NEEDS_NUMBA
def test_cpu_8x8_kernels_match_reference_on_deep_stacks():
    """Hundreds of Gaussians per 8x8 tile, many saturating pixels (early termination checked
    every 4th Gaussian, last index kept as float32), image edges cutting tiles: the
    specialised 8x8 kernels against the dense reference, images and gradients."""
    sc = make_scene(N=500, W=35, H=21, C=2, seed=11, scale=0.12, spread=0.8)
    sc["opacities"] = sc["opacities"].clamp_min(0.3)
    ref, fast = render(sc, "reference"), render(sc, "cpu")
    assert (fast["alphas"] > 0.98).float().mean() > 0.3  # deep, saturated stacks
    assert_images_close(fast, ref)
    assert_grads_close(fast["grads"], ref["grads"])


def test_torch_tiled_matches_reference():
    sc = make_scene(N=80, W=41, H=27, C=2, seed=4, sh_degree=1)
    ref, tiled = render(sc, "reference"), render(sc, "torch")
    assert_images_close(tiled, ref)
    assert_grads_close(tiled["grads"], ref["grads"])


def test_torch_tiled_recomputes_chunks_of_a_large_render_with_the_same_result(monkeypatch):
    """Above GRAPH_ELEMENTS each chunk is checkpointed (the paper's 1080x720 with 300k Gaussians
    needs over 24 GiB otherwise): its forward runs again in the backward, and images and
    gradients are those of the path that keeps every chunk."""
    from engine.raster import reference, torch_tiled
    sc = make_scene(N=300, W=64, H=40, C=2, seed=7, sh_degree=1)
    calls = []
    real = reference.composite_lists
    monkeypatch.setattr(torch_tiled, "composite_lists", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(torch_tiled, "CHUNK_ELEMENTS", 1 << 12)  # several chunks at this size
    kept = render(sc, "torch")
    n_kept = len(calls)
    assert n_kept > 2
    monkeypatch.setattr(torch_tiled, "GRAPH_ELEMENTS", 0)
    calls.clear()
    recomputed = render(sc, "torch")
    assert len(calls) == 2 * n_kept  # every chunk once forward, once again in the backward
    torch.testing.assert_close(recomputed["colors"], kept["colors"], atol=0, rtol=0)
    torch.testing.assert_close(recomputed["alphas"], kept["alphas"], atol=0, rtol=0)
    for name, g in kept["grads"].items():
        torch.testing.assert_close(recomputed["grads"][name], g, atol=1e-12, rtol=1e-9)


@NEEDS_NUMBA
@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_cpu_matches_reference_sh(sh_degree):
    sc = make_scene(N=60, C=2, seed=10 + sh_degree, sh_degree=sh_degree)
    ref, fast = render(sc, "reference"), render(sc, "cpu")
    assert_images_close(fast, ref)
    assert_grads_close(fast["grads"], ref["grads"])


@NEEDS_NUMBA
def test_background_and_no_depth():
    sc = make_scene(N=50, C=2, seed=5)
    bg = torch.tensor([[0.2, 0.5, 0.9], [1.0, 0.0, 0.3]])
    ref = render(sc, "reference", backgrounds=bg, render_depth=False)
    fast = render(sc, "cpu", backgrounds=bg, render_depth=False)
    assert "depths" not in fast["meta"]
    assert_images_close(fast, ref)
    assert_grads_close(fast["grads"], ref["grads"])
    # background shows exactly through the transmittance
    black = render(sc, "cpu", grads=False)
    expect = black["colors"] + (1 - black["alphas"]) * bg[:, None, None, :]
    torch.testing.assert_close(fast["colors"], expect, atol=1e-6, rtol=0)


@NEEDS_NUMBA
def test_fused_background_and_depth_match_reference_with_background_grads():
    """The cpu path blends the background and divides the expected depth inside its one
    autograd node (``finish_image`` / ``finish_grads``); a background that requires grad
    goes through torch instead. Images, depths and every gradient, the background's
    included, against the dense reference, with depth on and a background per camera."""
    sc = make_scene(N=60, C=2, seed=15)
    out = {}
    for backend in ("reference", "cpu"):
        for learn in (False, True):
            bg = torch.tensor([[0.2, 0.5, 0.9], [1.0, 0.0, 0.3]], requires_grad=learn)
            r = render(sc, backend, backgrounds=bg)
            if learn:
                r["grads"]["bg"] = bg.grad
            out[backend, learn] = r
    for learn in (False, True):
        assert_images_close(out["cpu", learn], out["reference", learn])
        assert_grads_close(out["cpu", learn]["grads"], out["reference", learn]["grads"])
    assert out["cpu", True]["grads"]["bg"].abs().sum() > 0


@NEEDS_NUMBA
@pytest.mark.parametrize("alpha_max", [0.99, 0.999])
def test_alpha_max_and_opaque_stack(alpha_max):
    """Opaque Gaussians stacked in depth: alpha clamp, transmittance stop, clamped grads."""
    sc = make_scene(N=40, seed=6, scale=0.3, spread=0.2)
    sc["opacities"] = torch.full((40,), 0.9999)
    ref = render(sc, "reference", alpha_max=alpha_max)
    fast = render(sc, "cpu", alpha_max=alpha_max)
    assert_images_close(fast, ref)
    assert_grads_close(fast["grads"], ref["grads"])
    assert fast["alphas"].max() >= 1 - 1e-3
    # one opaque Gaussian: its centre pixel has alpha exactly alpha_max
    one = make_scene(N=1, W=9, H=9, seed=0, scale=0.5)
    one["means"] = torch.tensor([[0.0, 0.0, 0.0]])
    one["opacities"] = torch.tensor([1.0])
    one["Ks"] = torch.tensor([[[9.0, 0, 4.5], [0, 9.0, 4.5], [0, 0, 1]]])
    out = render(one, "cpu", alpha_max=alpha_max)
    assert abs(out["alphas"][0, 4, 4, 0].item() - alpha_max) < 1e-6
    assert_grads_close(out["grads"], render(one, "reference", alpha_max=alpha_max)["grads"])


@NEEDS_NUMBA
def test_tile_size_does_not_change_result():
    sc = make_scene(N=70, W=45, H=31, C=2, seed=7)
    # tile 8 runs the specialised 8x8 kernels (FMA-contracted), tile 16 the generic ones:
    # equal to float32 rounding (depth ~5 m: a few ulp)
    a, b = render(sc, "cpu", tile_size=8), render(sc, "cpu", tile_size=16)
    assert_images_close(a, b, atol=2e-6, depth_atol=5e-5)
    assert_grads_close(a["grads"], b["grads"], rel=1e-4)


@pytest.mark.slow
def test_gradcheck_reference_float64():
    sc = make_scene(N=4, W=7, H=6, C=2, seed=8, sh_degree=1, dtype=torch.float64, scale=0.3,
                    spread=0.5)
    base = [sc[k].clone() for k in PARAMS]

    def f(means, quats, scales, opacities, colors):
        c, a, m = rasterization(means, quats, scales, opacities, colors, sc["viewmats"], sc["Ks"],
                                sc["width"], sc["height"], sh_degree=1, backend="reference",
                                backgrounds=torch.tensor([[0.1, 0.2, 0.3]] * 2, dtype=torch.float64))
        return c, a, m["depths"]

    inputs = tuple(t.requires_grad_() for t in base)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-3)


@pytest.mark.slow
@NEEDS_NUMBA
def test_cpu_float64_inputs_give_float64_outputs():
    sc = make_scene(N=30, seed=9, dtype=torch.float64)
    ref, fast = render(sc, "reference"), render(sc, "cpu")
    assert fast["colors"].dtype == torch.float64
    assert fast["grads"]["means"].dtype == torch.float64
    assert_images_close(fast, ref)
    assert_grads_close(fast["grads"], ref["grads"])


# ------------------------------------------------------------------------- edge cases

@NEEDS_NUMBA
@pytest.mark.parametrize("backend", ["cpu", "torch", "reference"])
def test_behind_camera_and_near_plane_no_nan(backend):
    sc = make_scene(N=30, seed=11)
    m = sc["means"].clone()
    m[:10, 2] = -4.0 - torch.linspace(0.0, 2.0, 10)      # camera z ~ 0 (at/behind the camera)
    m[10:12, 2] = -4.0 + 0.01                             # right at the near plane
    m[12:14] = torch.tensor([0.0, 0.0, -4.0])           # exactly at the camera centre
    m[14:16, 2] = -9.0                                  # far behind
    sc["means"] = m
    out = render(sc, backend)
    for k in ("colors", "alphas"):
        assert torch.isfinite(out[k]).all()
    assert torch.isfinite(out["meta"]["depths"]).all()
    for k, g in out["grads"].items():
        assert torch.isfinite(g).all(), k
    assert (out["meta"]["radii"][0, 12:16] == 0).all()


@NEEDS_NUMBA
@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_tiny_huge_scales_and_extreme_opacities(backend):
    sc = make_scene(N=40, seed=12)
    s = sc["scales"].clone()
    s[:8] = 1e-8             # degenerate: eps2d keeps them a ~0.5 px blob
    s[8:10] = 50.0           # covers everything (camera inside for some)
    s[10:12, 0] = 1e-7       # flat discs
    sc["scales"] = s
    o = sc["opacities"].clone()
    o[12:16] = 1e-6          # invisible: culled by opacity
    o[16:20] = 1.0           # clamped at alpha_max
    sc["opacities"] = o
    out = render(sc, backend)
    assert torch.isfinite(out["colors"]).all() and torch.isfinite(out["alphas"]).all()
    for k, g in out["grads"].items():
        assert torch.isfinite(g).all(), k
    assert (out["meta"]["radii"][0, 12:16] == 0).all()
    if backend == "cpu":
        assert_images_close(out, render(sc, "reference", grads=False))


@NEEDS_NUMBA
@pytest.mark.parametrize("backend", ["cpu", "torch", "reference"])
def test_empty_and_all_culled(backend):
    sc = make_scene(N=0, C=2)
    out = render(sc, backend)
    assert out["colors"].shape == (2, sc["height"], sc["width"], 3)
    assert (out["colors"] == 0).all() and (out["alphas"] == 0).all()
    assert out["meta"]["means2d"].shape == (2, 0, 2) and out["meta"]["radii"].shape == (2, 0)
    sc = make_scene(N=10, C=2)
    sc["means"] = sc["means"] * 0 + torch.tensor([0.0, 0.0, -10.0])  # all behind both cameras
    bg = torch.tensor([[0.3, 0.3, 0.3], [0.0, 1.0, 0.0]])
    out = render(sc, backend, backgrounds=bg)
    assert (out["meta"]["radii"] == 0).all()
    torch.testing.assert_close(out["colors"], bg[:, None, None, :].expand_as(out["colors"]))
    assert (out["meta"]["depths"] == 0).all()
    for g in out["grads"].values():
        assert g is not None and (g == 0).all()


@NEEDS_NUMBA
def test_gaussian_covering_full_image_and_odd_sizes():
    for W, H in [(13, 11), (8, 8), (9, 17), (1, 1)]:
        sc = make_scene(N=3, W=W, H=H, seed=13, scale=2.0, spread=0.1)
        sc["opacities"] = torch.tensor([0.9, 0.6, 0.7])
        sc["scales"] = torch.tensor([[4.0, 2.5, 3.0], [3.0, 4.5, 2.0], [2.5, 3.5, 5.0]])
        ref, fast = render(sc, "reference"), render(sc, "cpu")
        assert fast["colors"].shape == (1, H, W, 3)
        assert (fast["alphas"] > 0.5).all()
        assert_images_close(fast, ref)
        assert_grads_close(fast["grads"], ref["grads"])


@NEEDS_NUMBA
def test_offscreen_gaussians_culled_but_edge_ones_kept():
    sc = make_scene(N=4, W=20, H=20, seed=14, scale=0.05)
    sc["means"] = torch.tensor([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [2.3, 0.0, 0.0], [0.0, -2.3, 0.0]])
    sc["Ks"] = torch.tensor([[[18.0, 0, 10.0], [0, 18.0, 10.0], [0, 0, 1]]])
    sc["viewmats"] = torch.tensor(look_viewmat((0, 0, -4.0)), dtype=torch.float32)[None]
    ref, fast = render(sc, "reference"), render(sc, "cpu")
    radii = fast["meta"]["radii"][0]
    assert radii[0] > 0 and radii[1] == 0
    assert_images_close(fast, ref)
    assert_grads_close(fast["grads"], ref["grads"])


# ------------------------------------------------------------------- backend selection

@pytest.mark.parametrize("built", [False, True])
def test_gsplat_without_its_cuda_extension_falls_back(monkeypatch, built):
    """gsplat >= 1.0 builds its CUDA code on first use and, with no CUDA toolkit, leaves its
    extension None: "available" must mean the extension loaded, or training would crash at
    the first render instead of using the CPU path. A stand-in gsplat package (never the
    real one: it would try to build)."""
    import types

    pkg, cuda_pkg, backend = (types.ModuleType(n) for n in ("gsplat", "gsplat.cuda", "gsplat.cuda._backend"))
    backend._C = object() if built else None
    pkg.cuda, cuda_pkg._backend = cuda_pkg, backend
    for name, mod in (("gsplat", pkg), ("gsplat.cuda", cuda_pkg), ("gsplat.cuda._backend", backend)):
        monkeypatch.setitem(sys.modules, name, mod)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(gsplat_backend, "_gsplat", None)
    monkeypatch.setattr(gsplat_backend, "_error", None)
    assert gsplat_backend.available() is built
    if built:
        assert resolve_backend("auto", torch.device("cuda")) == "gsplat"
    else:
        assert "nvcc" in gsplat_backend.unavailable_reason()
        assert resolve_backend("auto", torch.device("cuda")) == "torch"  # the path that runs anywhere


def test_gsplat_never_imported_without_cuda():
    if torch.cuda.is_available():
        pytest.skip("CUDA present")
    assert not gsplat_backend.available()
    assert "CUDA" in gsplat_backend.unavailable_reason()
    assert "gsplat" not in sys.modules
    assert resolve_backend("auto", torch.device("cpu")) in ("cpu", "torch")
    with pytest.raises(ValueError):
        resolve_backend("vulkan", torch.device("cpu"))


def test_lazy_kernels_import_once_and_report_why_not():
    from engine.numba_cache import LazyKernels
    missing = LazyKernels("engine", "no_such_kernels")
    assert missing.load() is None and not missing.available()
    assert missing.unavailable_reason().startswith("ModuleNotFoundError")
    ok = LazyKernels("engine", "colour")  # any importable module: loaded once, then reused
    assert ok.load() is ok.load() is sys.modules["engine.colour"] and ok.unavailable_reason() == ""


def test_numba_missing_falls_back_to_torch_with_warning(monkeypatch):
    import engine.raster as raster
    monkeypatch.setattr(raster_cpu.KERNELS, "module", None)
    monkeypatch.setattr(raster_cpu.KERNELS, "error", ImportError("No module named 'numba'"))
    monkeypatch.setattr(raster, "_warned", set())
    sc = make_scene(N=30, seed=15)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        out = render(sc, "cpu")
    assert out["meta"]["backend"] == "torch"
    assert any("numba" in str(w.message) for w in rec)
    assert_images_close(out, render(sc, "reference", grads=False))


@pytest.mark.skipif(not gsplat_backend.available(), reason="needs CUDA + gsplat")
def test_gsplat_matches_cpu():
    sc = make_scene(N=200, W=64, H=48, C=2, seed=16, sh_degree=2, scale=0.05)
    cpu_out = render(sc, "cpu" if raster_cpu.available() else "torch", alpha_max=0.99)
    cuda = {k: (v.cuda() if torch.is_tensor(v) else v) for k, v in sc.items()}
    gs = render(cuda, "gsplat")
    assert gs["meta"]["backend"] == "gsplat"
    # gsplat's alpha cap is its own (0.99 / 0.999): compare loosely
    torch.testing.assert_close(gs["colors"].cpu(), cpu_out["colors"], atol=2e-2, rtol=0)
    torch.testing.assert_close(gs["alphas"].cpu(), cpu_out["alphas"], atol=2e-2, rtol=0)
    for k in PARAMS:
        a, b = gs["grads"][k].cpu(), cpu_out["grads"][k]
        cos = torch.nn.functional.cosine_similarity(a.reshape(-1), b.reshape(-1), dim=0)
        assert cos > 0.95, k


@NEEDS_NUMBA
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_numba_projection_matches_torch_projection(dtype):
    """Values and gradients of the hand-written projection backward, including depth-culled,
    FOV-clamped (far off to the side) and degenerate-quaternion Gaussians."""
    sc = make_scene(N=40, C=3, seed=17, dtype=dtype, spread=1.5)
    m = sc["means"].clone()
    m[:4, 2] = -4.0 - torch.tensor([0.0, 0.005, 1.0, 3.0], dtype=dtype)  # at / behind camera 0
    m[4:8, 0] = torch.tensor([8.0, -9.0, 12.0, -7.0], dtype=dtype)      # outside 1.3x FOV
    sc["means"] = m
    q = sc["quats"].clone()
    q[8] = 0.0
    sc["quats"] = q
    from engine.raster.cpu import project
    outs = []
    for fn in (project_gaussians, project):
        ps = [sc[k].clone().requires_grad_() for k in ("means", "quats", "scales")]
        p = fn(ps[0], ps[1], ps[2], sc["opacities"], sc["viewmats"], sc["Ks"], sc["width"],
               sc["height"])
        g = torch.Generator().manual_seed(3)
        w1 = torch.randn(p.means2d.shape, generator=g, dtype=dtype)
        w2 = torch.randn(p.conics.shape, generator=g, dtype=dtype)
        w3 = torch.randn(p.z.shape, generator=g, dtype=dtype)
        ((p.means2d * w1).sum() + (p.conics * w2).sum() + (p.z * w3).sum()).backward()
        outs.append((p, [x.grad for x in ps]))
    (pa, ga), (pb, gb) = outs
    tol = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(pb.means2d, pa.means2d, **tol)
    torch.testing.assert_close(pb.conics, pa.conics, **tol)
    torch.testing.assert_close(pb.z, pa.z, **tol)
    torch.testing.assert_close(pb.radii_xy, pa.radii_xy)
    assert (pb.radii[0, :4] == 0).all() and (pb.means2d[0, :4] == 0).all()
    assert (pb.radii[:, 9:] > 0).any()
    for a, b in zip(ga, gb):
        scale = a.abs().max().item()
        assert (a - b).abs().max().item() <= (2e-4 if dtype == torch.float32 else 1e-9) * scale


@NEEDS_NUMBA
def test_numba_projection_chunks_match_torch_projection():
    """The projection kernels run SIMD loops over chunks of PROJ_CHUNK Gaussians: more
    Gaussians than a chunk, not a multiple of it, two cameras, some below the opacity
    threshold and some behind a camera, in float64 (exact to 1e-10 of torch's)."""
    from engine.raster import _kernels as kern
    from engine.raster.cpu import project
    n = 2 * kern.PROJ_CHUNK + 37
    sc = make_scene(N=n, C=2, seed=5, dtype=torch.float64, spread=2.0)
    m = sc["means"].clone()
    m[::50, 2] = -4.5  # behind camera 0 (its eye is at z = -4)
    op = sc["opacities"].clone()
    op[::31] = 0.002  # below 1/255: radius 0
    outs = []
    for fn in (project_gaussians, project):
        ps = [t.clone().requires_grad_() for t in (m, sc["quats"], sc["scales"])]
        p = fn(ps[0], ps[1], ps[2], op, sc["viewmats"], sc["Ks"], sc["width"], sc["height"])
        g = torch.Generator().manual_seed(4)
        ((p.means2d * torch.randn(p.means2d.shape, generator=g, dtype=torch.float64)).sum()
         + (p.conics * torch.randn(p.conics.shape, generator=g, dtype=torch.float64)).sum()
         + (p.z * torch.randn(p.z.shape, generator=g, dtype=torch.float64)).sum()).backward()
        outs.append((p, [x.grad for x in ps]))
    (pa, ga), (pb, gb) = outs
    assert (pa.radii > 0).sum() > n // 2 and (pa.radii == 0).any()
    tol = dict(rtol=1e-10, atol=1e-10)
    for name in ("means2d", "conics", "z"):
        torch.testing.assert_close(getattr(pb, name), getattr(pa, name), **tol)
    torch.testing.assert_close(pb.radii_xy, pa.radii_xy)
    for a, b in zip(ga, gb):
        assert (a - b).abs().max().item() <= 1e-9 * a.abs().max().item()


@NEEDS_NUMBA
def test_numba_cache_is_per_import_name(tmp_path, monkeypatch):
    """Blender imports the engine as bl_ext.<repo>.bullettime4d.engine, the CLI as engine:
    their numba caches must not share entries (a cached entry pickles the import name).
    Both compiled modules: the rasterizer kernels and the PNG row decoder."""
    import importlib

    from engine.io import images
    from engine.raster import _kernels
    pkg = tmp_path / "bt4d_alias_pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "engine").symlink_to(Path(_kernels.__file__).resolve().parents[1], target_is_directory=True)
    monkeypatch.syspath_prepend(str(tmp_path))
    alias_kernels = importlib.import_module("bt4d_alias_pkg.engine.raster._kernels")
    alias_images = importlib.import_module("bt4d_alias_pkg.engine.io.images")
    a = _kernels.rasterize_fwd._cache._cache_path
    b = alias_kernels.rasterize_fwd._cache._cache_path
    assert a != b
    assert a.endswith("numba-engine.raster._kernels")
    assert b.endswith("numba-bt4d_alias_pkg.engine.raster._kernels")
    pa = images._unfilter_impl()._cache._cache_path
    pb = alias_images._unfilter_impl()._cache._cache_path
    assert pa.endswith("numba-engine.io.images")
    assert pb.endswith("numba-bt4d_alias_pkg.engine.io.images")


def test_warmup_runs_a_tiny_render():
    from engine.raster import warmup
    assert warmup("cpu" if raster_cpu.available() else "torch") >= 0.0


@NEEDS_NUMBA
def test_depth_order_is_a_stable_argsort_of_the_visible():
    """The binning's radix sort against numpy's stable argsort: ties (kept in index order),
    negative depths and -0.0 (a near plane below zero), several cameras, nothing visible."""
    rng = np.random.default_rng(0)
    for C, N in [(1, 5000), (3, 700), (2, 0), (1, 1), (2, 9)]:
        d = (rng.random((C, N)) * 4 + 2).astype(np.float32)
        if N > 8:
            d[0, : N // 3] = d[0, 0]
            d[-1, 3:9] = [-0.5, 0.0, -0.0, -3.0, 1e-30, np.float32(7e37)]
        r = (rng.random((C * N, 2)) > 0.2).astype(np.int32) * 3
        got = raster_cpu.depth_order(r, d)
        vis = r[:, 0].reshape(C, N) > 0
        ref = [np.flatnonzero(vis[c])[np.argsort(d[c][vis[c]], kind="stable")] + c * N
               for c in range(C)]
        assert got.dtype == np.int64
        np.testing.assert_array_equal(got, np.concatenate(ref) if ref else np.zeros(0))
    none = raster_cpu.depth_order(np.zeros((4, 2), np.int32), np.ones((1, 4), np.float32))
    assert none.shape == (0,)


@NEEDS_NUMBA
@pytest.mark.parametrize("tile_size", [8, 16])
def test_backward_kernels_write_every_intersection_row(tile_size):
    """The per-intersection gradient buffer is allocated uninitialised: the backward kernels
    must write every row, zeros for Gaussians behind a tile's last contributor (saturated
    pixels), or the gradient scatter would add garbage to the Gaussians' gradients."""
    sc = make_scene(N=300, W=24, H=16, seed=12, scale=0.15, spread=0.6)
    sc["opacities"] = sc["opacities"].clamp_min(0.5)
    proj = raster_cpu.project(sc["means"], sc["quats"], sc["scales"], sc["opacities"],
                              sc["viewmats"], sc["Ks"], 24, 16)
    feats = torch.cat([sc["colors"][None], proj.depths[..., None]], -1).float().contiguous()
    ops = sc["opacities"][None].float()
    binning = raster_cpu.bin_gaussians(proj.means2d, proj.conics, ops, proj.radii_xy,
                                       proj.depths, 24, 16, tile_size)
    offsets, ids, spans, tx, ty = binning
    k = raster_cpu._load()
    packed = np.empty((ids.shape[0], 10), np.float32)
    n = proj.means2d.shape[1]
    k.pack(proj.means2d.detach().numpy().reshape(n, 2), proj.conics.detach().numpy().reshape(n, 3),
           ops.numpy().reshape(n), feats.numpy().reshape(n, 4), ids, packed)
    out_f, out_a = np.zeros((1, 16, 24, 4), np.float32), np.zeros((1, 16, 24), np.float32)
    final_t, last_i = np.ones((1, 16, 24), np.float32), np.full((1, 16, 24), -1, np.int32)
    k.rasterize_fwd(packed, spans, offsets, 1, 16, 24, tile_size, tx, ty, 0.99, out_f, out_a,
                    final_t, last_i)
    assert (last_i[0] + 1 < np.diff(offsets)[np.arange(16)[:, None] // tile_size * tx
                                             + np.arange(24)[None] // tile_size]).any()
    v_isect = np.full((ids.shape[0], 10), np.nan, np.float32)
    k.rasterize_bwd(packed, spans, offsets, 1, 16, 24, tile_size, tx, ty, 0.99, final_t, last_i,
                    np.ones((1, 16, 24, 4), np.float32), np.ones((1, 16, 24), np.float32), v_isect)
    assert np.isfinite(v_isect).all()


@NEEDS_NUMBA
def test_backward_row_pairs_cover_each_span_inside_the_tile():
    """The 8x8 backward visits tile rows two at a time: an odd span is widened by one row,
    inside the tile, never narrowed (a dropped row would lose gradient)."""
    k = raster_cpu._load()
    for r0 in range(8):
        for r1 in range(r0 + 1, 9):
            a, b = k._even_rows(r0 | (r1 << 8))
            assert 0 <= a <= r0 and r1 <= b <= 8 and (b - a) % 2 == 0
            assert (b - a) - (r1 - r0) <= 1


@NEEDS_NUMBA
def test_backward_row_pairs_match_the_generic_kernel_on_every_span():
    """The 8x8 backward visits a Gaussian's tile rows two at a time (an odd span widened by
    a row): spans of every length and start must give the per-intersection gradients of
    the generic kernel (one row at a time), which sees the same spans."""
    sc = make_scene(N=400, W=40, H=32, seed=23, scale=0.05, spread=0.9)
    proj = raster_cpu.project(sc["means"], sc["quats"], sc["scales"], sc["opacities"],
                              sc["viewmats"], sc["Ks"], 40, 32)
    feats = torch.cat([sc["colors"][None], proj.depths[..., None]], -1).float().contiguous()
    ops = sc["opacities"][None].float()
    offsets, ids, spans, tx, ty = raster_cpu.bin_gaussians(
        proj.means2d, proj.conics, ops, proj.radii_xy, proj.depths, 40, 32, 8)
    r0, r1 = spans & 255, spans >> 8
    assert {(a, b) for a, b in zip(r0.tolist(), r1.tolist())} >= {(a, a + n) for n in (1, 2, 3)
                                                                 for a in range(0, 9 - n)}
    k = raster_cpu._load()
    n = proj.means2d.shape[1]
    packed = np.empty((ids.shape[0], 10), np.float32)
    k.pack(proj.means2d.detach().numpy().reshape(n, 2), proj.conics.detach().numpy().reshape(n, 3),
           ops.numpy().reshape(n), feats.numpy().reshape(n, 4), ids, packed)
    out_f, out_a = np.zeros((1, 32, 40, 4), np.float32), np.zeros((1, 32, 40), np.float32)
    final_t, last_i = np.ones((1, 32, 40), np.float32), np.full((1, 32, 40), -1, np.int32)
    k.rasterize_fwd(packed, spans, offsets, 1, 32, 40, 8, tx, ty, 0.99, out_f, out_a, final_t, last_i)
    g = np.random.default_rng(2)
    v_feat = g.standard_normal((1, 32, 40, 4)).astype(np.float32)
    v_alpha = g.standard_normal((1, 32, 40)).astype(np.float32)
    grads = []
    for kernel in (k._bwd_tile8, k._bwd_tile):
        v = np.full((ids.shape[0], 10), np.nan, np.float32)
        for tile in range(tx * ty):
            if kernel is k._bwd_tile8:
                kernel(tile, packed, spans, offsets, 32, 40, tx, tx * ty, np.float32(0.99),
                       final_t, last_i, v_feat, v_alpha, v)
            else:
                kernel(tile, packed, spans, offsets, 32, 40, 8, tx, tx * ty, np.float32(0.99),
                       final_t, last_i, v_feat, v_alpha, v)
        grads.append(v)
    assert np.isfinite(grads[0]).all() and np.abs(grads[1]).max() > 0
    scale = np.abs(grads[1]).max(0)
    assert (np.abs(grads[0] - grads[1]) <= 1e-4 * scale + 1e-6).all()


@NEEDS_NUMBA
@pytest.mark.parametrize("n_isect", [7, 900])
def test_pack_split_gathers_each_intersections_record(n_isect):
    """``pack_split`` takes two routes: fewer intersections than Gaussians gather straight
    from the arrays, more assemble per-Gaussian records first. Both give the same rows."""
    k = raster_cpu._load()
    g = np.random.default_rng(9)
    C, N = 2, 150
    m2d, con = g.random((C * N, 2), np.float32), g.random((C * N, 3), np.float32)
    op, rgb, z = g.random(N, np.float32), g.random((C * N, 3), np.float32), g.random(C * N, np.float32)
    ids = g.integers(0, C * N, n_isect).astype(np.int32)
    packed = np.full((n_isect, 10), np.nan, np.float32)
    k.pack_split(m2d, con, op, rgb, z, N, ids, packed)
    expect = np.concatenate([m2d[ids], con[ids], op[ids % N, None], rgb[ids], z[ids, None]], 1)
    np.testing.assert_array_equal(packed, expect)


@NEEDS_NUMBA
def test_composite_tiles_matches_composite_dense():
    """``cpu.composite_tiles`` (raw feature sums, any channel count <= 4; ``rasterization``
    now runs ``rasterize_fused``) keeps the contract of ``reference.composite_dense``:
    images and gradients of 3 channels, two cameras."""
    from engine.raster.reference import composite_dense

    sc = make_scene(N=50, W=30, H=22, C=2, seed=21)
    proj = project_gaussians(sc["means"], sc["quats"], sc["scales"], sc["opacities"],
                             sc["viewmats"], sc["Ks"], 30, 22)
    g = torch.Generator().manual_seed(3)
    feats0 = torch.rand(2, 50, 3, generator=g)
    ops0 = sc["opacities"][None].expand(2, -1).contiguous()
    out = {}
    for name, fn, radii in (("dense", composite_dense, proj.radii),
                            ("tiles", raster_cpu.composite_tiles, proj.radii_xy)):
        m2d, feats, ops = (t.detach().clone().requires_grad_(True)
                           for t in (proj.means2d, feats0, ops0))
        img, alpha = fn(m2d, proj.conics.detach(), ops, feats, proj.depths.detach(), radii, 30, 22)
        (img * torch.linspace(0, 1, 3) + alpha).sum().backward()
        out[name] = (img, alpha, m2d.grad, feats.grad, ops.grad)
    assert out["tiles"][1].max() > 0.5
    for a, b in zip(out["tiles"], out["dense"]):
        torch.testing.assert_close(a, b, atol=2e-5, rtol=2e-3)
