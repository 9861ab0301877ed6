"""engine.scene.observed: Gaussians no train camera constrained, and Scene4D.prune (issue 14
floaters at new viewpoints; the Blender side is tested through render_path in
tests/test_orbit_strip.py)."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from export_util import write_run

from engine.cameras import Intrinsics, look_at_c2w
from engine.errors import RunError
from engine.io.capture import Frame
from engine.scene.model import load_run
from engine.scene.observed import centre_inside, prune_unobserved, unobserved_mask


def _pair(scene, times=(0.0, 0.2)):
    """A stereo pair 0.4 m apart, 2 m in front of the (moving) cloud's middle, with a narrow
    view: part of the cloud lies outside both images."""
    k = Intrinsics(40, 30, 80.0, 80.0, 20.0, 15.0)
    c = np.median(scene.gaussians_at(float(np.mean(times)))["means"], axis=0).astype(np.float64)
    frames = []
    for t in times:
        for name, x in (("left", -0.2), ("right", 0.2)):
            eye = c + np.array([x, -2.0, 0.0])
            frames.append(Frame(Path(f"/nowhere/{name}_{t}.png"), name, float(t),
                                look_at_c2w(eye, eye + np.array([0.0, 2.0, 0.0])), k))
    return frames


def test_centre_inside_respects_the_inset_and_the_camera_side():
    k = Intrinsics(40, 30, 80.0, 80.0, 20.0, 15.0)
    f = Frame(Path("/nowhere/a.png"), "a", 0.0, look_at_c2w([0, -2, 0], [0, 0, 0]), k)
    v = f.view()
    # world points at the image centre, 3 px from the left edge, and behind the camera
    z = 2.0
    pts = np.array([[0.0, 0.0, 0.0], [(3.0 - 20.0) * z / 80.0, 0.0, 0.0], [0.0, -4.0, 0.0]])
    np.testing.assert_array_equal(centre_inside(pts, v, 0.0), [True, True, False])
    np.testing.assert_array_equal(centre_inside(pts, v, 4.0), [True, False, False])


def test_unobserved_mask_matches_a_per_gaussian_check(tmp_path):
    scene = load_run(write_run(tmp_path / "run", n=400))
    frames = _pair(scene)
    one = unobserved_mask(scene, frames, inset_px=0.0, min_cameras=1)
    # brute force: per Gaussian, the cameras that see its centre at any frame
    seen = {}
    for f in frames:
        m = scene.gaussians_at(f.time)["means"]
        v = f.view()
        q = m @ v.viewmat[:3, :3].T + v.viewmat[:3, 3]
        u = v.intrinsics.fx * q[:, 0] / q[:, 2] + v.intrinsics.cx
        w = v.intrinsics.fy * q[:, 1] / q[:, 2] + v.intrinsics.cy
        ok = (q[:, 2] > 0) & (u >= 0) & (u <= 40) & (w >= 0) & (w <= 30)
        seen[f.camera] = seen.get(f.camera, np.zeros(len(m), bool)) | ok
    expect_one = ~(seen["left"] | seen["right"])
    np.testing.assert_array_equal(one, expect_one)
    assert 0 < one.sum() < len(one)  # the narrow pair misses part of the box, sees the rest
    two = unobserved_mask(scene, frames, inset_px=0.0, min_cameras=2)
    np.testing.assert_array_equal(two, ~(seen["left"] & seen["right"]))
    assert (two >= one).all() and two.sum() > one.sum()
    inset = unobserved_mask(scene, frames, inset_px=5.0)
    assert (inset >= one).all() and inset.sum() > one.sum()
    with pytest.raises(ValueError, match="no train frames"):
        unobserved_mask(scene, [])


def test_prune_drops_exactly_the_masked_gaussians(tmp_path):
    run = write_run(tmp_path / "run", n=300)
    scene, ref = load_run(run), load_run(run)
    n_static = 7
    for s in (scene, ref):  # static Gaussians (frozen in time) are pruned with their flag
        s.model.static_mask = torch.zeros(300, dtype=torch.bool)
        s.model.static_mask[:n_static] = True
    frames = _pair(scene)
    mask = unobserved_mask(scene, frames)
    n = prune_unobserved(scene, SimpleNamespace(frames=frames))
    assert n == int(mask.sum()) and scene.num_gaussians == 300 - n
    assert scene.info["pruned_unobserved"] == {"pruned": n, "left": 300 - n, "inset_px": 4.0, "min_cameras": 1}
    assert int(scene.model.static_mask.sum()) == int((~mask[:n_static]).sum())
    assert not unobserved_mask(scene, frames).any()  # what is left is all observed
    # the pruned scene renders as the original with those Gaussians made transparent
    with torch.no_grad():
        ref.model.gaussians.opacity_logits[torch.as_tensor(mask)] = -1e4
    for f in frames[:2]:
        a = scene.render([f.view()], background=(0, 0, 0))[0]
        b = ref.render([f.view()], background=(0, 0, 0))[0]
        np.testing.assert_allclose(a["rgb"], b["rgb"], atol=1e-5)
        np.testing.assert_allclose(a["alpha"], b["alpha"], atol=1e-5)
    with pytest.raises(ValueError, match="prune mask"):
        scene.prune(np.zeros(3, bool))


def test_prune_needs_a_capture(tmp_path):
    scene = load_run(write_run(tmp_path / "run", n=20))
    with pytest.raises(RunError, match="no capture recorded"):
        prune_unobserved(scene)
