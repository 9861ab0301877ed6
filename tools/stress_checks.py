"""Stress suite, part 2: the check cases (fixed work, no optimiser): extreme spike
streams, float32 vs float64, bad capture inputs, and the real trainer at two scene scales.
"""
from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from engine.errors import CaptureError
from engine.io.capture import load_capture
from engine.io.spikes import read_spikes, write_spikes
from engine.spike import render as sr
from engine.spike.simulate import simulate_spikes, tfi, tfp
from engine.train import train
from engine.train.loop.trainer import LOSS_FACTORIES

from .stress_cases import PARAM_ORDER, CaseResult, count_nonfinite, make_camera, random_params, render_raw
from .synthetic import write_moving_capture, write_tiny_capture

# ----------------------------------------------------------------------------- check cases

def case_spikes_extreme(steps, tick, seed=0):
    """All-zero and all-one spike streams through the simulator, reconstructions, IO and the
    differentiable spike renderer."""

    res = CaseResult("spikes_extreme")
    t0 = time.perf_counter()
    H, W, n = 12, 16, 64
    streams = {
        "zero": simulate_spikes(np.zeros((H, W)), rate_hz=20000.0, num_frames=n, seed=seed),
        "one": simulate_spikes(np.full((H, W), 5.0), rate_hz=20000.0, num_frames=n, seed=seed),
    }
    if streams["zero"].any():
        res.failures.append("zero light produced spikes")
    if not streams["one"].all():
        res.failures.append("saturating light did not fire every frame")
    streams["zero"][:] = 0
    streams["one"][:] = 1
    with tempfile.TemporaryDirectory(prefix="bt4d_stress_") as tmp:
        for kind, s in streams.items():
            rec = [tfp(s), tfp(s, 8, index=0), tfp(s, 8, index=n - 1), tfi(s, 0), tfi(s, n // 2),
                   tfi(s, n - 1), tfi(s, n // 2, max_window=3)]
            res.nonfinite_other += sum(count_nonfinite(np.asarray(r, dtype=np.float64)) for r in rec)
            want = 0.0 if kind == "zero" else 1.0
            if not all(np.allclose(r, want) for r in rec):
                res.failures.append(f"{kind} stream: tfp/tfi not all {want}")
            path = Path(tmp) / f"{kind}.dat"
            write_spikes(path, s)
            if not np.array_equal(read_spikes(path, H, W), s):
                res.failures.append(f"{kind} stream: write/read round trip differs")
    sensor = sr.SensorModel(width=W, height=H, scale=0.5, dark_current=0.0, threshold=1.0)
    rend = sr.SpikeRenderer(sensor)
    for kind, s in streams.items():
        obs = torch.from_numpy(s.astype(np.float32))
        obs_counts = obs.sum(0)
        # black, grey, saturated renders (sigmoid of a raw image) and an unbounded one
        # (values from -1 to 3: out-of-range renders must not break sRGB decoding)
        for init in (-30.0, 0.0, 30.0, None):
            if init is None:
                raw = torch.linspace(-1.0, 3.0, 2 * H * 2 * W * 3).reshape(2 * H, 2 * W, 3).requires_grad_(True)
            else:
                raw = torch.full((2 * H, 2 * W, 3), init, requires_grad=True)
            opt = torch.optim.Adam([raw], lr=0.05)
            for step in range(max(1, steps // 8)):
                opt.zero_grad()
                img = raw if init is None else torch.sigmoid(raw)
                counts = rend.render_counts(img, n)
                spikes = rend.render_spikes(img, m=16, generator=torch.Generator().manual_seed(step))
                loss = sr.spike_count_loss(counts, obs_counts, n) \
                    + sr.cumulative_spike_loss(spikes, obs[:16])
                res.nonfinite_other += count_nonfinite(loss) + count_nonfinite(counts)
                loss.backward()
                gb = res.tally_grad(raw.grad)
                opt.step()
                pb = count_nonfinite(raw)
                res.nonfinite_params += pb
                if (gb or pb) and res.first_bad_step is None:
                    res.first_bad_step = res.steps
                res.steps += 1
                res.final_loss = float(loss.detach())
        # sensor fit from all-zero / all-one rates and black / white images
        for luma_v in (0.0, 1.0):
            luma = np.full((3, H, W), luma_v)
            rates = np.broadcast_to(s.mean(0, dtype=np.float64), (3, H, W))
            fit = sr.fit_sensor(luma, rates, width=W, height=H)
            vals = [fit.scale, fit.dark_current, fit.info.get("fit_l1_rate", 0.0)]
            n_bad = sum(0 if math.isfinite(float(v)) else 1 for v in vals)
            n_bad += count_nonfinite(fit.gain) if fit.gain is not None else 0
            res.nonfinite_other += n_bad
            if n_bad:
                res.failures.append(f"fit_sensor({kind} stream, luma {luma_v}) is not finite")
    if tick is not None:
        tick(steps)
    res.seconds = time.perf_counter() - t0
    return res


def compare_fp32_fp64(seed: int = 0, n: int = 12, size: int = 16) -> dict:
    """Fast path (float32, ``cpu``) vs dense reference (float64) on one random scene.

    Returns max abs differences of image / alpha / depth and the relative L2 error of each
    parameter's gradient under the same loss."""
    p64 = random_params(n, seed=seed, dtype=torch.float64)
    cam = make_camera(3.0, size)
    g = torch.Generator().manual_seed(seed + 5)
    target = torch.rand(size, size, 3, generator=g, dtype=torch.float64)
    out = {}
    grads = {}
    for name, backend, dtype in (("fast32", "cpu", torch.float32), ("ref64", "reference", torch.float64)):
        leaves = {k: v.to(dtype).clone().requires_grad_(True) for k, v in p64.items()}
        rgb, alpha, meta = render_raw(leaves, cam, backend=backend)
        loss = ((rgb - target.to(dtype)) ** 2).mean() + 1e-2 * meta["depths"].mean()
        loss.backward()
        out[name] = (rgb.detach().double(), alpha.detach().double(), meta["depths"][0].detach().double())
        grads[name] = {k: v.grad.detach().double() for k, v in leaves.items()}
    a, b = out["fast32"], out["ref64"]
    res = {"image": float((a[0] - b[0]).abs().max()), "alpha": float((a[1] - b[1]).abs().max()),
           "depth": float((a[2] - b[2]).abs().max())}
    for k in PARAM_ORDER:
        ga, gb = grads["fast32"][k], grads["ref64"][k]
        res[f"grad_{k}"] = float((ga - gb).norm() / gb.norm().clamp_min(1e-12))
        res[f"nonfinite_{k}"] = count_nonfinite(ga) + count_nonfinite(gb)
    return res


# tolerances for fp32_vs_fp64 (float32 compositing vs float64 dense reference)
FP_TOL = {"image": 2e-4, "alpha": 2e-4, "depth": 2e-3, "grad": 2e-3}


def case_fp32_vs_fp64(steps, tick, seed=0):
    res = CaseResult("fp32_vs_fp64")
    t0 = time.perf_counter()
    n_scenes = max(1, min(20, steps // 10))
    worst = {}
    for i in range(n_scenes):
        r = compare_fp32_fp64(seed * 1000 + i)
        for k, v in r.items():
            if k.startswith("nonfinite_"):
                res.nonfinite_grads += int(v)
            else:
                worst[k] = max(worst.get(k, 0.0), v)
        res.steps += 1
    for k, v in worst.items():
        tol = FP_TOL["grad"] if k.startswith("grad_") else FP_TOL[k]
        if not v <= tol:
            res.failures.append(f"{k} differs by {v:.2e} (> {tol:.0e})")
    res.notes.append("max diff: " + ", ".join(f"{k} {v:.1e}" for k, v in worst.items()))
    res.final_loss = float("nan")
    res.seconds = time.perf_counter() - t0
    if tick is not None:
        tick(steps)
    return res


def bad_input_checks(tmp: Path) -> list[dict]:
    """Each bad input -> dict(name, rejected, names_file, message, leaked). ``leaked`` counts
    non-finite values that reached the caller (0 when rejected)."""

    nan, inf = float("nan"), float("inf")
    bad_pose = np.eye(4)
    bad_pose[0, 3] = nan
    inf_pose = np.eye(4)
    inf_pose[1, 1] = inf
    nan_img = np.full((8, 8, 3), 0.5, np.float32)
    nan_img[2, 3, 1] = nan
    inf_img = np.full((8, 8, 3), 0.5, np.float32)
    inf_img[4, 4, 0] = inf
    variants = {
        "pose_nan": dict(pose=bad_pose.tolist()),
        "pose_inf": dict(pose=inf_pose.tolist()),
        "intrinsics_nan": dict(fl_x=nan),
        "time_nan": dict(time_value=nan),
        "image_exr_nan": dict(image=nan_img, exr=True),
        "image_exr_inf": dict(image=inf_img, exr=True),
    }
    out = []
    for name, kw in variants.items():
        root = tmp / name
        tpath = write_tiny_capture(root, **kw)
        rec = {"name": name, "rejected": False, "names_file": False, "message": "", "leaked": 0}
        try:
            cap = load_capture(root)
            views = [cap.view(f) for f in cap.frames]
            imgs = [f.load_rgb() for f in cap.frames]
            rec["leaked"] = sum(count_nonfinite(v.c2w) + count_nonfinite(np.asarray(v.K)) +
                                (0 if math.isfinite(v.time) else 1) for v in views)
            rec["leaked"] += sum(count_nonfinite(np.asarray(i, dtype=np.float32)) for i in imgs)
            if rec["leaked"] == 0 and name.startswith("image_exr_inf"):
                rec["rejected"] = False  # inf clipped to 1 by the sRGB encode: not a leak
                rec["message"] = "accepted (inf clipped to 1.0)"
        except CaptureError as exc:
            rec["rejected"] = True
            rec["message"] = str(exc)
            culprit = (root / "f0.exr") if name.startswith("image") else tpath
            rec["names_file"] = culprit.name in str(exc)
        out.append(rec)
    return out


def case_bad_inputs(steps, tick, seed=0):
    res = CaseResult("bad_inputs")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bt4d_stress_") as tmp:
        for rec in bad_input_checks(Path(tmp)):
            res.steps += 1
            res.nonfinite_other += rec["leaked"]
            if rec["leaked"]:
                res.failures.append(f"{rec['name']}: {rec['leaked']} non-finite values accepted")
            elif rec["rejected"] and not rec["names_file"]:
                res.failures.append(f"{rec['name']}: error does not name the file: {rec['message']}")
            elif not rec["rejected"]:
                res.notes.append(f"{rec['name']}: {rec['message'] or 'accepted'}")
    res.seconds = time.perf_counter() - t0
    if tick is not None:
        tick(steps)
    return res


def case_trainer(steps, tick, seed=0):
    """The real trainer (``engine.train.train``, fast preset, both stages, densification) on a
    tiny synthetic capture at scene scale 1 and 1e-3; parameters and gradients of the
    Gaussians and the deformation field are checked after every step."""

    res = CaseResult("trainer")
    t0 = time.perf_counter()
    state = {"run": None}

    def grab(run):
        state["run"] = run
        return []

    factories = (*LOSS_FACTORIES, grab)  # the run's own loss terms, plus one that grabs its run context
    with tempfile.TemporaryDirectory(prefix="bt4d_stress_") as tmp:
        for scale, n in ((1.0, min(steps, 150)), (1e-3, min(steps, 40))):
            if n < 2:
                continue
            cap = write_moving_capture(Path(tmp) / f"cap{scale:g}", scale, seed)

            def progress(p):
                tr = state["run"]
                named = dict(tr.model.gaussians.params())
                if tr.model.deformation is not None:
                    named.update({f"field.{k}": v for k, v in tr.model.deformation.named_parameters()})
                bad = 0
                for t in named.values():
                    bad += count_nonfinite(t)
                    res.nonfinite_params += count_nonfinite(t)
                    if t.grad is not None:
                        bad += res.tally_grad(t.grad)
                res.nonfinite_other += count_nonfinite(float(p["loss"]))
                if bad and res.first_bad_step is None:
                    res.first_bad_step = res.steps
                res.steps += 1
                res.final_loss = float(p["loss"])

            out = train(cap, Path(tmp) / f"run{scale:g}", preset="fast", resume=False, seed=seed,
                        progress=progress, loss_factories=factories, overrides={"iterations": n, "init_max_points": 300,
                                                      "init_random_points": 100, "checkpoint_every_s": 1e9})
            res.notes.append(f"scale {scale:g}: {out['step']} steps, train PSNR {out['psnr']:.2f}, "
                             f"{out['num_gaussians']} Gaussians, init {out['init'].get('method')}")
    res.seconds = time.perf_counter() - t0
    if tick is not None:
        tick(steps)
    return res
