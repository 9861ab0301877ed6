"""Geometry terms of issue 14 (engine.geometry_losses): zero when consistent, gradients flow,
each switch takes part in a run."""
from __future__ import annotations

import cv2
import numpy as np
import torch

from engine.cameras import Intrinsics, View, look_at_c2w
from engine.train.losses import geometry_losses
from engine.train.losses.geometry_losses import decay_visible_opacity

W, H = 64, 48
K = Intrinsics(W, H, 60.0, 60.0, W / 2, H / 2)
_TEX = cv2.GaussianBlur(np.random.default_rng(3).random((400, 400)).astype(np.float32), (0, 0), 1.5)
_TEX = (_TEX - _TEX.min()) / (_TEX.max() - _TEX.min())


def _plane_view(x):
    view = View(K, look_at_c2w(np.array([x, 0.0, 0.0]), np.array([x, 2.0, 0.0])))
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    # fronto-parallel plane y = 2: planar depth 2 everywhere; texture fixed on the plane
    px = x + (u + 0.5 - K.cx) / K.fx * 2.0
    pz = -(v + 0.5 - K.cy) / K.fy * 2.0
    img = cv2.remap(_TEX, ((px + 2) / 4 * 399).astype(np.float32), ((pz + 2) / 4 * 399).astype(np.float32),
                    cv2.INTER_LINEAR)
    t = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    return t(np.repeat(img[..., None], 3, -1)), t(view.K), t(view.viewmat)


def test_opacity_decay_only_touches_visible_gaussians():
    logits = torch.zeros(5)
    decay_visible_opacity(logits, torch.tensor([True, False, True, False, False]), 0.9)
    op = torch.sigmoid(logits)
    assert torch.allclose(op[[0, 2]], torch.full((2,), 0.45)) and torch.allclose(op[[1, 3, 4]], torch.full((3,), 0.5))


def test_opacity_decay_acts_in_its_window_of_the_schedule():
    from types import SimpleNamespace

    from engine.train.config import get_preset
    from engine.train.loop.schedule import Schedule
    from engine.train.losses.geometry_losses import geometry_post_step_hooks

    cfg = get_preset("fast", {"opacity_decay": 0.9, "opacity_decay_until": 0.5, "iterations": 10,
                              "init_backdrop": 0.0})
    (hook,) = geometry_post_step_hooks(cfg)
    logits = torch.zeros(4)
    tr = SimpleNamespace(cfg=cfg, schedule=Schedule.plan(10),
                         model=SimpleNamespace(gaussians=SimpleNamespace(opacity_logits=logits, num_gaussians=4)))
    seen = {"radii": torch.ones(1, 4, dtype=torch.int32)}
    hook(tr, 4, {}, seen)
    assert torch.allclose(torch.sigmoid(logits), torch.full((4,), 0.45))  # step 4 of 10: inside [0, 5)
    hook(tr, 5, {}, seen)  # step 5 of 10: past the end, opacities are the photometric loss's again
    assert torch.allclose(torch.sigmoid(logits), torch.full((4,), 0.45))
    # a budget run re-planned to 20 real steps at step 2: the window is on the schedule's clock
    # (virtual step 2 + (s - 2) * 8 / 18), not on cfg.schedule.iterations: real step 8 is virtual 4.7
    tr.schedule.replan(2, 20)
    logits.zero_()
    hook(tr, 8, {}, seen)
    assert torch.allclose(torch.sigmoid(logits), torch.full((4,), 0.45))
    hook(tr, 14, {}, seen)  # virtual 7.3: past the end
    assert torch.allclose(torch.sigmoid(logits), torch.full((4,), 0.45))


def test_opacity_decay_ends_with_densification_unless_told():
    from engine.train.config import get_preset, opacity_decay_window
    from engine.train.losses.geometry_losses import geometry_post_step_hooks

    assert get_preset("fast").losses.opacity_decay_until is None
    assert opacity_decay_window(get_preset("fast")) == (0.0, get_preset("fast").densify.stop)
    assert opacity_decay_window(get_preset("fast", {"densify_until": 0.5})) == (0.0, 0.5)  # follows it
    assert opacity_decay_window(get_preset("fast", {"densify_until": 0.5, "opacity_decay_until": 0.9})) == (0.0, 0.9)
    # a --set from the command line arrives as a string and becomes a float
    assert get_preset("fast", {"opacity_decay_until": "1"}).losses.opacity_decay_until == 1.0
    from types import SimpleNamespace

    from engine.train.loop.schedule import Schedule
    for until, decayed_at_6 in ((0.5, False), (0.8, True)):
        cfg = get_preset("fast", {"opacity_decay": 0.9, "densify_until": until, "iterations": 10,
                                  "init_backdrop": 0.0})
        (hook,) = geometry_post_step_hooks(cfg)
        logits = torch.zeros(2)
        tr = SimpleNamespace(cfg=cfg, schedule=Schedule.plan(10),
                             model=SimpleNamespace(gaussians=SimpleNamespace(opacity_logits=logits, num_gaussians=2)))
        hook(tr, 6, {}, {"radii": torch.ones(1, 2, dtype=torch.int32)})
        assert bool((logits != 0).all()) == decayed_at_6


def test_every_switch_takes_part_in_a_run(tmp_path, monkeypatch):
    from engine.io.capture import load_capture
    from engine.train import train
    from engine.train.config import get_preset
    from engine.train.loop.trainer import Trainer
    from engine.train.losses.terms import default_loss_terms
    from tools.synthetic import write_synthetic_capture

    monkeypatch.setattr(geometry_losses, "COVER_EVERY", 1)
    monkeypatch.setattr(geometry_losses, "BACKDROP_OPACITY", 0.0)  # the one post-step hook below is opacity decay
    on = {"opacity_decay": 0.99, "lambda_depth": 0.1, "lambda_cover": 0.5, "init": "stereo", "init_backdrop": 0.2,
          "losses.flat": 0.02}
    names = [t.name for t in default_loss_terms(get_preset("fast", on))]
    assert {"stereo_depth", "cover", "flat"} <= set(names)
    # a 0.6 m baseline: the pair resolves the set's depth (>= 8 px of disparity) and the planes are fitted
    cap = load_capture(write_synthetic_capture(tmp_path / "cap", width=48, height=36, n_rgb=2, eval_fps=30.0,
                                               baseline=0.6))
    tr = Trainer(cap, get_preset("fast", {**on, "iterations": 4}), device="cpu", rgb_only=True)
    tr.init_model()
    assert tr.init_info["method"] == "stereo" and tr.init_info["backdrop"] > 0
    assert any("stereo_depth" in it for it in tr.items) and any("stereo_normal" in it for it in tr.items)
    out = tr.step(0)
    assert {"stereo_depth", "cover", "flat"} <= set(out["losses"])
    assert len(tr.post_step_hooks) == 1  # opacity decay, applied to what the step's view saw
    g = tr.model.gaussians
    n = g.num_gaussians
    radii = torch.zeros(1, n, dtype=torch.int32)
    radii[0, : n // 2] = 3
    before = torch.sigmoid(g.opacity_logits.detach()).clone()
    tr.post_step_hooks[0](tr, 1, tr.items[0], {"radii": radii})
    after = torch.sigmoid(g.opacity_logits.detach())
    assert torch.allclose(after[: n // 2], before[: n // 2] * 0.99, atol=1e-5)
    assert torch.equal(after[n // 2:], before[n // 2:])
    train(cap, tmp_path / "run", overrides={**on, "iterations": 3}, rgb_only=True)
    from engine.io.checkpoint import read_run_json

    info = read_run_json(tmp_path / "run")
    assert info["config"]["losses"]["cover"] == 0.5 and info["init"]["backdrop"] > 0


def test_orbit_view_turns_about_the_point_the_view_looks_at():
    import math

    from engine.train.losses.geometry_losses import orbit_view

    vm = torch.eye(4)[None]
    vm[0, :3, :3] = torch.tensor([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])  # some rotation
    vm[0, :3, 3] = torch.tensor([0.3, -0.2, 2.5])
    K = torch.tensor([[[120.0, 0, 64], [0, 110.0, 48], [0, 0, 1]]])
    vt = {"viewmat": vm, "K": K, "width": 128, "height": 96, "campos": torch.zeros(3), "time": 0.25,
          "image": torch.zeros(1, 96, 128, 3)}
    R = vm[0, :3, :3].double().T
    c = -R @ vm[0, :3, 3].double()
    pivot = c + 2.0 * R[:, 2]
    o = orbit_view(vt, 2.0, 0.7, math.radians(20), 0.5)
    R2 = o["viewmat"][0, :3, :3].double().T
    c2 = -R2 @ o["viewmat"][0, :3, 3].double()
    assert torch.allclose(o["campos"].double(), c2, atol=1e-5)
    assert abs(float((c2 - pivot).norm()) - 2.0) < 1e-5  # same distance to the pivot
    assert torch.allclose(c2 + 2.0 * R2[:, 2], pivot, atol=1e-5)  # and still looking at it
    cos = float(R[:, 2] @ R2[:, 2])
    assert abs(math.degrees(math.acos(min(1.0, cos))) - 20.0) < 1e-3
    assert o["width"] == 64 and o["height"] == 48 and "image" not in o and o["time"] == 0.25
    assert torch.allclose(o["K"], torch.tensor([[[60.0, 0, 32], [0, 55.0, 24], [0, 0, 1]]]))
    assert torch.equal(vt["K"], K)  # the step's view is left as it was


def test_cover_loss_sees_cracks_not_the_space_around_the_scene():
    from engine.train.losses.geometry_losses import cover_loss, crack_mask

    a = torch.zeros(40, 60)
    a[10:30, 10:50] = 1.0          # the scene's outline, empty space around it
    a[18:21, 10:50] = 0.0          # a crack 3 px wide through it
    a[24, 30] = 0.2                # a thin splat
    m = crack_mask(a, 9)
    assert bool(m[19, 30]) and bool(m[24, 30]) and not bool(m[5, 5]) and not bool(m[35, 55])
    alpha = a.clone().requires_grad_(True)
    loss = cover_loss(alpha, 9)
    assert abs(float(loss.detach()) - (3 * 40 + 0.8) / a.numel()) < 1e-6
    loss.backward()
    assert float(alpha.grad[19, 30]) < 0 and float(alpha.grad[5, 5]) == 0.0  # raise alpha in the crack only
    assert cover_loss(torch.zeros(8, 8), 3) is None
    # a band along the image border is the view looking past the scene's edge, not a crack
    edge = torch.ones(20, 20)
    edge[:2] = 0.0
    edge[:, -3:] = 0.0
    m = crack_mask(edge, 9)
    assert not bool(m[:2].any()) and not bool(m[:, -3:].any()) and bool(m[10, 10])


def test_crack_mask_separable_closing_matches_the_square_box():
    """The two 1-D pools per pass give the k x k box's closing exactly (border empty)."""
    import torch.nn.functional as F

    from engine.train.losses.geometry_losses import crack_mask

    g = torch.Generator().manual_seed(3)
    for k in (3, 9, 21):
        a = (torch.rand(37, 53, generator=g) > 0.35).float() * torch.rand(37, 53, generator=g)
        r = k // 2
        m = F.pad((a > 0.5).float()[None, None], (r, r, r, r))
        dil = F.max_pool2d(m, k, stride=1, padding=r)
        ref = (-F.max_pool2d(-dil, k, stride=1, padding=r))[0, 0, r:r + 37, r:r + 53] > 0.5
        assert torch.equal(crack_mask(a, k), ref), k


def test_cover_kernel_follows_the_render_resolution(tmp_path, monkeypatch):
    """The closing box is a share of the virtual render's shorter side: the 9 px measured on
    the test scenes, 45 px at a 1080x720 capture's 540x360 render; and the term passes the
    render's own size to it."""
    from engine.io.capture import load_capture
    from engine.train.config import get_preset
    from engine.train.loop.trainer import Trainer
    from engine.train.losses import geometry_losses as gl
    from tools.synthetic import write_synthetic_capture

    frac = gl.COVER_KERNEL_FRAC
    assert gl.cover_kernel_px(frac, 60, 80) == 9 and gl.cover_kernel_px(frac, 72, 96) == 9  # the test scenes
    assert gl.cover_kernel_px(frac, 360, 540) == 45  # a 1080x720 capture
    assert gl.cover_kernel_px(frac, 120, 160) == 15
    assert gl.cover_kernel_px(frac, 10, 12) == 3  # never below 3 px
    seen = []
    real = gl.cover_loss
    monkeypatch.setattr(gl, "cover_loss", lambda alpha, kernel, eligible=None: (
        seen.append((tuple(alpha.shape), kernel)), real(alpha, kernel, eligible))[1])
    cap = load_capture(write_synthetic_capture(tmp_path / "cap", width=96, height=72, n_rgb=2, eval_fps=30.0))
    monkeypatch.setattr(gl, "COVER_EVERY", 1)
    for frac, want in ((0.125, 5), (0.3, 11)):  # COVER_SCALE 0.5: 48x36 renders
        seen.clear()
        monkeypatch.setattr(gl, "COVER_KERNEL_FRAC", frac)
        cfg = get_preset("fast", {"iterations": 4})
        tr = Trainer(cap, cfg, device="cpu", seed=0, rgb_only=True)
        tr.init_model()
        for s in range(2):
            tr.step(s)
        assert seen and all(sh == (36, 48) and k == want for sh, k in seen), seen


def test_cover_term_raises_alpha_at_a_new_view(tmp_path, monkeypatch):
    """A short run with the cover term leaves fewer cracks at a view 20 deg off than without."""
    import math

    from engine.io.capture import load_capture
    from engine.train.config import get_preset
    from engine.train.loop.trainer import Trainer
    from engine.train.losses.geometry_losses import crack_mask, orbit_view
    from tools.synthetic import write_synthetic_capture

    cap = load_capture(write_synthetic_capture(tmp_path / "cap", width=48, height=36, n_rgb=2, eval_fps=30.0))
    holes = {}
    monkeypatch.setattr(geometry_losses, "COVER_EVERY", 1)
    monkeypatch.setattr(geometry_losses, "COVER_SCALE", 1.0)
    for lam in (0.0, 4.0):
        cfg = get_preset("fast", {"iterations": 40, "lambda_cover": lam,
                                  "densify_until": 0.0, "opacity_decay": 1.0})
        tr = Trainer(cap, cfg, device="cpu", seed=0, rgb_only=True)
        tr.init_model()
        for s in range(40):
            out = tr.step(s)
        assert ("cover" in out["losses"]) == (lam > 0)
        total = 0.0
        with torch.no_grad():
            for k, ang in enumerate((0.0, 1.6, 3.1, 4.7)):
                it = tr.items[k % len(tr.items)]
                _, a0, meta, _ = tr.model.render(it, float(it["time"]), render_depth=True)
                pivot = float(meta["depths"][0, ..., 0][a0[0, ..., 0] > 0.5].median())
                vt = orbit_view(it, pivot, ang, math.radians(20))
                _, alpha, _, _ = tr.model.render(vt, float(it["time"]), render_depth=False)
                a = alpha[0, ..., 0]
                total += float(((1 - a) * crack_mask(a, 9)).sum())
        holes[lam] = total
    print(holes)
    assert holes[4.0] < holes[0.0]


def test_seen_from_marks_what_the_source_view_sees():
    import math

    from engine.train.losses.geometry_losses import orbit_view, seen_from

    vm = torch.eye(4)[None]
    vm[0, 2, 3] = 2.0
    vt = {"viewmat": vm, "K": torch.tensor([[[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]]]), "width": 100,
          "height": 80, "campos": torch.tensor([0.0, 0, -2]), "time": 0.0}
    assert bool(seen_from(vt, vt, 2.0).all())
    turned = orbit_view(vt, 2.0, math.pi / 2, math.radians(40))  # about the camera's y axis: sideways
    m = seen_from(turned, vt, 2.0)
    assert m.shape == (80, 100) and bool(m[40, 50]) and 0.2 < float(m.float().mean()) < 0.95
    assert bool(m[:, 0].all()) != bool(m[:, -1].all())  # one side leaves the source's frustum


def test_render_grad_rows_limits_the_gradient_to_those_gaussians(tmp_path):
    from engine.io.capture import load_capture
    from engine.train.config import get_preset
    from engine.train.loop.trainer import Trainer
    from tools.synthetic import write_synthetic_capture

    cap = load_capture(write_synthetic_capture(tmp_path / "cap", width=32, height=24, n_rgb=2, eval_fps=30.0))
    tr = Trainer(cap, get_preset("fast", {"iterations": 2}), device="cpu", seed=0, rgb_only=True)
    tr.init_model()
    g = tr.model.gaussians
    rows = torch.zeros(g.num_gaussians, dtype=torch.bool)
    rows[::2] = True
    _, alpha, _, _ = tr.model.render(tr.items[0], render_depth=False, grad_rows=rows)
    alpha.sum().backward()
    grad = g.opacity_logits.grad.reshape(g.num_gaussians)
    assert bool((grad[~rows] == 0).all()) and bool((grad[rows] != 0).any())


def test_render_grad_attrs_limits_the_gradient_to_those_attributes(tmp_path):
    """``grad_attrs``: a loss on the render trains only the named attributes (the cover term's
    ``cover_grad``, e.g. positions and opacities, not the shapes); "size": the scales' common
    factor only."""
    from engine.io.capture import load_capture
    from engine.train.config import get_preset
    from engine.train.loop.trainer import Trainer
    from tools.synthetic import write_synthetic_capture

    cap = load_capture(write_synthetic_capture(tmp_path / "cap", width=32, height=24, n_rgb=2, eval_fps=30.0))
    tr = Trainer(cap, get_preset("fast", {"iterations": 2}), device="cpu", seed=0, rgb_only=True)
    tr.init_model()
    g = tr.model.gaussians
    for attrs, trained in ((("opacities", "means"), {"opacity_logits", "means"}),
                           (None, {"opacity_logits", "means", "log_scales", "quats"})):
        for p in (g.means, g.quats, g.log_scales, g.opacity_logits):
            p.grad = None
        _, alpha, _, _ = tr.model.render(tr.items[0], render_depth=False, grad_attrs=attrs)
        alpha.sum().backward()
        for name in ("means", "quats", "log_scales", "opacity_logits"):
            grad = getattr(g, name).grad
            moved = grad is not None and bool((grad != 0).any())
            assert moved == (name in trained), (attrs, name)
    # "size": one gradient shared by the three log-scales of a Gaussian, nothing else moves
    for p in (g.means, g.quats, g.log_scales, g.opacity_logits):
        p.grad = None
    _, alpha, _, _ = tr.model.render(tr.items[0], render_depth=False, grad_attrs=("size",))
    alpha.sum().backward()
    gs = g.log_scales.grad
    assert g.means.grad is None or not bool((g.means.grad != 0).any())
    assert bool((gs != 0).any()) and torch.allclose(gs, gs[:, :1].expand_as(gs), atol=1e-7)


def test_cover_grad_reaches_the_term_render(tmp_path, monkeypatch):
    """The cover term renders with ``grad_attrs`` from ``cover_grad``: all attributes by default,
    only positions and opacities with ``opacities+means`` (docs/experiments/cover-loss.md "What the term may
    change")."""
    from engine.io.capture import load_capture
    from engine.scene.model import Model4D
    from engine.train.config import get_preset
    from engine.train.loop.trainer import Trainer
    from tools.synthetic import write_synthetic_capture

    seen = []
    real = Model4D.render

    def spy(self, vt, t=None, **kw):
        if kw.get("grad_rows") is not None:  # only the cover term passes grad_rows
            seen.append(kw.get("grad_attrs"))
        return real(self, vt, t, **kw)

    monkeypatch.setattr(Model4D, "render", spy)
    cap = load_capture(write_synthetic_capture(tmp_path / "cap", width=48, height=36, n_rgb=2, eval_fps=30.0))
    for over, want in (({}, None), ({"cover_grad": "opacities+means"}, ("opacities", "means"))):
        seen.clear()
        monkeypatch.setattr(geometry_losses, "COVER_EVERY", 1)
        tr = Trainer(cap, get_preset("fast", {"iterations": 4, **over}), device="cpu", seed=0,
                     rgb_only=True)
        tr.init_model()
        tr.step(0)
        assert seen and all(a == want for a in seen), (over, seen)


def test_cover_grad_names_are_checked():
    import pytest

    from engine.train.losses.geometry_losses import cover_grad_attrs

    assert cover_grad_attrs("all") is None
    assert cover_grad_attrs("opacities+means") == ("opacities", "means")
    with pytest.raises(ValueError, match="opacity"):
        cover_grad_attrs("opacity+means")


def test_depth_normals_fit_a_tilted_plane_and_drop_depth_edges():
    from engine.geometry.depth_priors import depth_normals

    k = np.array([[70.0, 0, 40], [0, 70.0, 30], [0, 0, 1]])
    v, u = np.mgrid[0:60, 0:80] + 0.5
    x = (u - 40) / 70
    z = 2.0 / (1 - 0.5 * x)                                    # the plane z = 2 + 0.5 X (camera space)
    n, ok, off = depth_normals(z, np.ones_like(z, bool), k)
    assert np.allclose(off[ok], -2.0 / np.linalg.norm([0.5, 0.0, -1.0]), atol=1e-3)  # n . x = off on the plane
    want = np.array([0.5, 0.0, -1.0]) / np.linalg.norm([0.5, 0.0, -1.0])  # facing the camera
    assert ok[5:-5, 5:-5].all() and np.allclose(n[ok], want, atol=1e-3)
    step = np.where(u < 40, 2.0, 3.0)                            # two walls, one a metre behind the other
    n, ok, _ = depth_normals(step, np.ones_like(step, bool), k)
    assert not ok[:, 37:42].any() and ok[10:50, 10:36].all() and ok[10:50, 42:70].all()  # none across the edge
    assert np.allclose(n[ok], [0, 0, -1], atol=1e-6)
    sparse = np.random.default_rng(0).random(z.shape) < 0.2    # too few known pixels in a box: no normal
    assert not depth_normals(z, sparse, k)[1].any()


def _disc_item(normal_world, offset):
    """A camera at the origin looking down +z (OpenCV), a wall at z = 2 whose stereo plane is given."""
    h, w = 30, 40
    return {"viewmat": torch.eye(4)[None], "K": torch.tensor([[[40.0, 0, 20], [0, 40.0, 15], [0, 0, 1]]]),
            "width": w, "height": h, "stereo_depth": torch.full((h, w), 2.0),
            "stereo_normal": torch.tensor(normal_world, dtype=torch.float32).expand(h, w, 3).contiguous(),
            "stereo_offset": torch.full((h, w), float(offset))}


def test_lie_flat_is_zero_for_a_disc_on_the_surface_and_trains_fins_and_strays_onto_it():
    from engine.train.losses.geometry_losses import lie_flat

    item = _disc_item([0.0, 0.0, -1.0], -2.0)                        # the plane -z = -2
    means = torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.0, 2.0], [0.0, 0.1, 2.5]])  # on, on, 25 % behind
    disc = torch.tensor([[1.0, 0, 0, 0]] * 3)                          # axes = world axes: thin along z
    scales = torch.tensor([[0.02, 0.02, 0.001]] * 3)
    assert float(lie_flat(means, disc, scales, item)) < 1e-2
    # a fin: the same shape turned 80 degrees about y, nearly thin along x and standing out of the wall
    a = np.radians(80) / 2
    fin = torch.tensor([[np.cos(a), 0, np.sin(a), 0]] * 3, dtype=torch.float32, requires_grad=True)
    assert abs(float(lie_flat(means, fin, scales, item).detach()) - 0.5) < 0.03
    assert lie_flat(means[2:], fin[2:], scales[2:], item) is None  # behind the surface: not on it
    assert lie_flat(means, disc, scales, {**item, "stereo_normal": torch.zeros(30, 40, 3)}) is None
    # a disc 1.5 cm in front of the wall (within the band): its offset counts, as a share of its spread
    stray = means.clone()
    stray[:2, 2] = 1.985
    assert 0.2 < float(lie_flat(stray, disc, scales, item)) < 0.25  # 1.5^2 / (2 * 2^2 + 1.5^2)
    stray.requires_grad_(True)
    opt = torch.optim.Adam([fin, stray], lr=0.002)
    for _ in range(400):
        opt.zero_grad()
        lie_flat(stray, fin, scales, item).backward()
        opt.step()
    assert float(lie_flat(stray, fin, scales, item).detach()) < 0.02  # turned to lie on the wall, and onto it
    assert torch.allclose(stray[:2, 2].detach(), torch.tensor(2.0), atol=2e-3)


def test_in_gaussian_frame_matches_the_rotation_matrices():
    from engine.scene.gaussians import quat_to_rotmat
    from engine.train.losses.geometry_losses import in_gaussian_frame

    g = torch.Generator().manual_seed(4)
    q = torch.randn(64, 4, generator=g, dtype=torch.float64) * 3
    v = torch.randn(64, 3, generator=g, dtype=torch.float64)
    want = (quat_to_rotmat(q).transpose(1, 2) @ v[:, :, None])[..., 0]
    assert torch.allclose(in_gaussian_frame(q, v), want, atol=1e-12)


def test_world_planes_of_a_wide_frame_are_fitted_on_a_subsample_and_agree():
    from engine.geometry.depth_priors import world_planes

    h, w = 240, 900
    k = np.array([[700.0, 0, 450.3], [0, 700.0, 119.6], [0, 0, 1]])
    v, u = np.mgrid[0:h, 0:w] + 0.5
    x, y = (u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1]
    depth = np.where(u < 450, 2.0, 3.0 / (1 - 0.4 * x - 0.2 * y))  # a wall, a metre-deep step, a tilted wall
    vm = np.eye(4)
    vm[:3, 3] = [0.1, -0.2, 0.3]
    full = world_planes(depth, np.ones_like(depth, bool), k, vm, max_width=10_000)
    sub = world_planes(depth, np.ones_like(depth, bool), k, vm)              # every 3rd pixel
    have = (np.abs(full[0]).sum(-1) > 0) & (np.abs(sub[0]).sum(-1) > 0)
    away = np.abs(u - 450) > 60                                              # the boxes (56 / 57 px) clear the step
    assert have[away].mean() > 0.9
    assert np.allclose(full[0][have & away], sub[0][have & away], atol=1e-4)
    assert np.allclose(full[1][have & away], sub[1][have & away], atol=1e-4)
    # the plane holds the frame's back-projected points: n . x = offset in world space
    cam = np.stack([x * depth, y * depth, depth], -1)
    world = (cam - vm[:3, 3]) @ vm[:3, :3]
    assert np.allclose((sub[0] * world).sum(-1)[have & away], sub[1][have & away], atol=1e-4)
