"""Scene flow of Gaussians between RGB instants from optical flow + stereo depth (issue 11)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from engine.cameras import Intrinsics, View, look_at_c2w, project_points
from engine.train.motion.scene_flow import backproject_pixels, carry_by_flow, image_flow


def _view():
    c2w = look_at_c2w((0.0, -5.0, 0.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0))
    return View(c2w=c2w, intrinsics=Intrinsics(80, 60, 70.0, 70.0, 40.0, 30.0), time=0.0)


def test_backproject_inverts_project():
    v = _view()
    pts = np.array([[0.1, 0.0, 0.2], [-0.5, 1.0, 0.3]])
    uv, z = project_points(v, pts)
    np.testing.assert_allclose(backproject_pixels(v, uv, z), pts, atol=1e-9)


def test_visible_moving_gaussians_follow_flow_and_depth_hidden_ones_stay():
    v = _view()
    depth_a = np.full((60, 80), 5.0, np.float32)
    ok = np.ones((60, 80), bool)
    depth_b = np.full((60, 80), 4.0, np.float32)  # the surface came 1 m closer
    flow = np.zeros((60, 80, 2), np.float32)
    flow[..., 0] = 7.0  # 7 px to the right
    pts = np.array([[0.0, 0.0, 0.0],     # on the surface (camera z 5)
                    [0.0, 2.0, 0.0],     # behind it (z 7): hidden, stays
                    [50.0, 0.0, 0.0]])   # outside the image, stays
    new, carried = carry_by_flow(pts, v, flow, depth_a, ok, depth_b, ok)
    assert carried.tolist() == [True, False, False]
    uv_a, _ = project_points(v, pts[:1])
    uv_b, z_b = project_points(v, new[:1])
    np.testing.assert_allclose(uv_b - uv_a, [[7.0, 0.0]], atol=1e-3)
    np.testing.assert_allclose(z_b, [4.0], atol=1e-4)
    np.testing.assert_array_equal(new[1:], pts[1:].astype(np.float32))
    # unconfident depth at the target, or no motion: not carried
    _, c = carry_by_flow(pts, v, flow, depth_a, ok, depth_b, np.zeros_like(ok))
    assert not c.any()
    _, c = carry_by_flow(pts, v, np.zeros_like(flow), depth_a, ok, depth_b, ok)
    assert not c.any()


@pytest.mark.parametrize("method", ["lk", "dis"])
def test_image_flow_finds_a_shift(method):
    rng = np.random.default_rng(0)
    base = rng.uniform(size=(16, 20, 3)).astype(np.float32)
    a = np.kron(base, np.ones((4, 4, 1), np.float32))  # 64x80, blocky texture
    b = np.roll(a, 3, axis=1)  # content moves 3 px right: a(p) = b(p + 3)
    f = image_flow(a, b, method)
    assert f.shape == (64, 80, 2)
    assert abs(float(np.median(f[8:-8, 8:-8, 0])) - 3.0) < 0.5 and abs(float(np.median(f[8:-8, 8:-8, 1]))) < 0.5


def test_hidden_gaussians_follow_their_nearest_decided_neighbour():
    from engine.train.motion.scene_flow import propagate_to_hidden

    pos = np.array([[0.0, 0, 0], [0.01, 0, 0], [1.0, 0, 0], [0.02, 0, 0], [5.0, 0, 0]])
    delta = np.zeros((5, 3), np.float32)
    delta[0] = [0.1, 0, 0]  # carried by flow
    decided = np.array([True, False, True, False, False])  # 2: a still surface (delta 0)
    out, taken = propagate_to_hidden(pos, delta, decided, max_dist=0.5)
    np.testing.assert_allclose(out[1], [0.1, 0, 0])
    np.testing.assert_allclose(out[3], [0.1, 0, 0])
    assert taken.tolist() == [False, True, False, True, False]  # 4 is too far from anything decided
    np.testing.assert_allclose(out[4], 0.0)


def test_still_surfaces_hold_moving_ones_move_the_rest_fall_back_to_velocity():
    """The carry's decision (junction_moves): a Gaussian a camera sees as a still surface holds
    (delta 0, placed) instead of being left to constant velocity, which compounded each instant's
    noise into a drift of the static world; a camera that sees it move wins over one that sees
    it still; hidden ones take a moved neighbour's delta; the rest fall back."""
    from engine.train.motion.scene_flow import junction_moves

    pos = np.array([[0.0, 0, 0],   # 0: moves in camera 0
                    [1.0, 0, 0],   # 1: a still surface in camera 0, nowhere carried: holds
                    [0.01, 0, 0],  # 2: hidden near 0: takes its move
                    [1.01, 0, 0],  # 3: hidden near the still 1: velocity fallback, as before
                    [5.0, 0, 0],   # 4: far from everything: velocity fallback
                    [3.0, 0, 0]], np.float32)  # 5: still in camera 0, moves in camera 1: moves
    moved = pos + np.float32(0.2)
    cam0 = (moved, np.array([1, 0, 0, 0, 0, 0], bool), np.array([0, 1, 0, 0, 0, 1], bool))
    cam1 = (moved, np.array([0, 0, 0, 0, 0, 1], bool), np.zeros(6, bool))
    delta, placed, held, by_flow = junction_moves(pos, [cam0, cam1], hidden_radius=0.1)
    assert placed.tolist() == [True, True, True, False, False, True]
    assert held.tolist() == [False, True, False, False, False, False]
    assert by_flow.tolist() == [True, False, False, False, False, True]
    np.testing.assert_allclose(delta[[0, 2, 5]], 0.2, atol=1e-6)
    np.testing.assert_array_equal(delta[1], 0.0)
    _, placed, _, _ = junction_moves(pos, [cam0, cam1], hidden_radius=0.0)  # no hand-over
    assert placed.tolist() == [True, True, False, False, False, True]


def test_image_flow_rejects_an_unknown_method():
    a = np.zeros((8, 8, 3), np.float32)
    with pytest.raises(ValueError, match="unknown optical flow method 'rift'"):
        image_flow(a, a, "rift")


def test_frame_image_is_the_trainers_copy_of_the_file(demo_capture):
    """The carry and the births read a train frame from trainer.items (loaded once per run)
    instead of the disk at each admission: the same numbers; a frame the trainer does not
    hold (e.g. held back by early stopping) still comes from the disk."""

    from engine.io.capture import load_capture
    from engine.train.loop.scene_setup import train_frames
    from engine.train.motion import scene_flow

    frames = train_frames(load_capture(demo_capture))
    held, other = frames[0], frames[1]
    disk = np.asarray(held.load_rgb(), np.float32)[..., :3]
    item = {"camera": held.camera, "time": float(held.time), "image": torch.from_numpy(disk.copy())[None]}
    from train_util import fake_run

    tr = fake_run(items=[item])
    got = scene_flow.frame_image(tr, held)
    assert np.shares_memory(got, item["image"].numpy()) and np.array_equal(got, disk)
    assert np.array_equal(scene_flow.frame_image(tr, other), np.asarray(other.load_rgb(), np.float32)[..., :3])
