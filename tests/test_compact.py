"""Compact 4D cache (engine/export/compact.py): error bounds, renders, size, bad files."""
from __future__ import annotations

import numpy as np
import pytest
from export_util import camera, moving_model, render_model

from engine.evaluate.metrics import psnr
from engine.export import compact
from engine.export.splats import SPLAT_KEYS, render_splats, splats_at
from engine.scene.model import view_tensors

TIMES = np.linspace(0.0, 0.2, 9)


@pytest.fixture(scope="module")
def model():
    return moving_model(n=400, sh_degree=1)


@pytest.fixture(scope="module")
def frames(model):
    return [splats_at(model, t) for t in TIMES]


@pytest.fixture(scope="module")
def cache_file(tmp_path_factory, frames):
    path = tmp_path_factory.mktemp("c") / "scene.bt4c"
    return compact.write_compact(path, TIMES, dict(zip(TIMES, frames)).__getitem__, meta={"source": "unit"})


def _unit_quats(q):
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def test_round_trip_error_is_within_half_a_step(cache_file, frames):
    c = compact.read_compact(cache_file)
    steps = c.header["steps"]
    assert len(c) == len(TIMES) and c.num_gaussians == 400 and c.meta == {"source": "unit"}
    np.testing.assert_allclose(c.times, TIMES)
    for i, f in enumerate(frames):
        got = c.splats(i)
        for k in SPLAT_KEYS:
            want = _unit_quats(f[k]) if k == "quats" else f[k]
            err = np.abs(got[k] - want).max()
            assert err <= steps[k] / 2 * (1 + 1e-4) + 1e-6, (k, i, err, steps[k])
            assert got[k].shape == np.shape(f[k]) and got[k].dtype == np.float32


def test_renders_match_the_model(cache_file, model):
    c = compact.read_compact(cache_file)
    for i in (0, 5, 8):
        view = camera(TIMES[i])
        got = render_splats(c.splats(i), view_tensors(view, "cpu"), model.background, model.near_plane)["rgb"]
        assert psnr(got, render_model(model, view)) > 40.0


def test_interpolates_between_instants(cache_file, frames):
    c = compact.read_compact(cache_file)
    mid = 0.5 * (TIMES[2] + TIMES[3])
    s = c.splats_at(mid)
    np.testing.assert_allclose(s["means"], 0.5 * (c.splats(2)["means"] + c.splats(3)["means"]), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(s["quats"], axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(c.splats_at(TIMES[4])["means"], c.splats(4)["means"])
    np.testing.assert_array_equal(c.splats_at(-1.0)["means"], c.splats(0)["means"])  # clamped
    np.testing.assert_array_equal(c.splats_at(9.0)["means"], c.splats(8)["means"])


def test_static_scene_costs_little_per_instant(frames):
    one = compact.encode(TIMES[:1], frames[:1])
    static = compact.encode(np.linspace(0, 1, 50), [frames[0]] * 50)
    moving = compact.encode(TIMES, frames)
    raw = sum(v.nbytes for v in frames[0].values())
    assert len(one) < raw / 2
    assert len(static) < 1.2 * len(one)  # residuals of a static scene are zero runs
    assert len(moving) < len(TIMES) * raw / 4


def test_coarser_steps_give_smaller_files_and_bigger_errors(frames):
    fine = compact.encode(TIMES, frames)
    coarse = compact.encode(TIMES, frames, steps={k: 8 * v for k, v in compact.DEFAULT_STEPS.items()})
    assert len(coarse) < len(fine)


def test_truncated_and_corrupted_files(tmp_path, cache_file):
    data = cache_file.read_bytes()
    for name, blob, pattern in [
        ("empty.bt4c", b"", "truncated"),
        ("short.bt4c", data[:10], "truncated: 10 bytes"),
        ("header.bt4c", data[:40], "truncated inside the header"),
        ("cut.bt4c", data[:-100], "truncated: .* bytes, the header promises"),
        ("magic.bt4c", b"XXXX" + data[4:], "not a BulletTime4D compact cache"),
    ]:
        (tmp_path / name).write_bytes(blob)
        with pytest.raises(compact.CompactFormatError, match=f"{name}: {pattern}"):
            compact.read_compact(tmp_path / name)
    flipped = bytearray(data)
    flipped[-50] ^= 0xFF
    (tmp_path / "flip.bt4c").write_bytes(bytes(flipped))
    with pytest.raises(compact.CompactFormatError, match="flip.bt4c: corrupted: block 'sh_residual' fails its CRC-32"):
        compact.read_compact(tmp_path / "flip.bt4c")
    newer = bytearray(data)
    newer[8:12] = (compact.VERSION + 1).to_bytes(4, "little")
    (tmp_path / "newer.bt4c").write_bytes(bytes(newer))
    with pytest.raises(compact.CompactFormatError, match="newer.bt4c: cache version 2 is newer"):
        compact.read_compact(tmp_path / "newer.bt4c")
    with pytest.raises(compact.CompactFormatError, match="missing.bt4c: compact cache does not exist"):
        compact.read_compact(tmp_path / "missing.bt4c")


def test_bad_input_to_the_encoder(frames):
    with pytest.raises(ValueError, match="one splat dict per time"):
        compact.encode(TIMES[:2], frames[:3])
    bad = dict(frames[1], means=frames[1]["means"].copy())
    bad["means"][0, 0] = np.nan
    with pytest.raises(ValueError, match="not finite"):
        compact.encode(TIMES[:2], [frames[0], bad])
    fewer = {k: v[:10] for k, v in frames[1].items()}
    with pytest.raises(ValueError, match="instant 1: Gaussian count"):
        compact.encode(TIMES[:2], [frames[0], fewer])


def test_failed_write_leaves_nothing(tmp_path, frames):
    def boom(t):
        raise RuntimeError("sampling failed")
    with pytest.raises(RuntimeError):
        compact.write_compact(tmp_path / "x.bt4c", TIMES, boom)
    assert list(tmp_path.iterdir()) == []


def test_cache_fills_holes_as_the_model_does(cache_file, model, tmp_path):
    """``eval --fill-holes`` on a cache scores the same picture as on the run: uncovered
    pixels take the covered neighbourhood's colour, not the background."""
    from engine.export.cached import CachedScene
    from engine.scene.model import Scene4D

    cached = CachedScene(cache_file)
    run = Scene4D(model, tmp_path, {})
    view = camera(TIMES[4])
    got = cached.render([view], background=model.background, fill_holes=True)[0]
    want = run.render([view], fill_holes=True)[0]
    bare = cached.render([view], background=model.background)[0]
    hole = bare["alpha"] < 1e-3
    assert hole.any() and (~hole).any()
    assert np.abs(got["rgb"][hole] - np.asarray(model.background, np.float32)).max() > 0.05
    assert psnr(got["rgb"], want["rgb"]) > 35.0
