"""Error against wall time (``python -m tools bench``), plus micro-benchmark ratios.

Design (documented here because the numbers depend on it):

* Each configuration -- a preset x a *variant* -- is one call of ``engine.train.train``
  with a wall-clock budget (``seconds``) in a fresh run directory ``OUT/<preset>-<variant>``.
  Variants: ``full`` (the method as configured, spike terms when the spike branch is
  registered), ``rgb_only`` (the RGB-only baseline), and the skip switches of the trainer
  (:data:`VARIANT_OVERRIDES`, ``TrainConfig``): ``freeze`` (``freeze_static``,
  :class:`engine.train.skipping.freezing.TrainFreezer`), ``early_stop`` (``early_stop``: stop when a
  held-out proxy stops improving, :class:`engine.train.skipping.early_stop.EarlyStop`) and ``cull``
  (``cull_frustum``: prune Gaussians outside every train frustum).
* **Curve samples are periodic checkpoints evaluated afterwards**: the run's
  ``checkpoint_every_s`` is set to ``eval_every_s``; every time the trainer writes a new
  ``checkpoint.pt`` the progress callback hard-links it into ``snapshots/`` (no copy; the
  trainer replaces the file atomically, so each link keeps one version). Nothing is
  evaluated inside the training loop, so the wall time of a run is not inflated by the
  measurement (the only in-loop cost is the trainer's own checkpoint writes). After
  training every snapshot is rendered on the capture's eval frames (every
  ``eval_stride``-th one) -> PSNR / SSIM at (wall seconds since ``train()`` was called,
  step). The final model gets the full ``engine.evaluate.evaluate`` (all eval frames:
  PSNR, SSIM, inter-frame and dynamic PSNR) and the static-region flicker
  (:func:`engine.evaluate.flicker.run_flicker`).
* Peak memory is the process's peak resident set size during the run (Linux ``VmHWM``,
  reset before each run through ``/proc/self/clear_refs``; elsewhere ``ru_maxrss``, the
  process-lifetime peak, flagged as such). torch CPU tensors are inside the RSS.
* Early stopping runs inside the trainer: its proxy is the PSNR on a few train frames held
  back from training (``engine.train.skipping.early_stop.PROXY_FRAMES``; never eval frames, so every
  eval figure here is on views the run neither trained on nor stopped by), evaluated every
  ``EVERY_FRACTION`` of the steps (its cost *is* counted in the wall time); training stops
  after ``skip.early_stop_patience`` proxy evaluations without a gain of ``MIN_DELTA_DB``,
  once the deformation stage has run for ``MIN_DEFORM_FRACTION`` of its steps.
* Micro-benchmarks in the same run: rasterizer fast path (``cpu``) vs the dense
  ``reference`` and the plain-PyTorch tiled path (``engine.cli.bench_raster``'s scene and
  timer), and spike decoding ``read_spikes`` vs the community per-frame loader and the
  per-byte Python loop (``engine.cli.bench_decode``), as speed ratios.

Outputs in OUT: ``bench.csv`` (one row per curve sample), ``bench.png`` (PSNR and SSIM
against wall time), ``bench.md`` (final table + micro-benchmarks), ``bench.json``.
"""
from __future__ import annotations

import json
import math
import os
import platform
import resource
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from engine.evaluate import evaluate
from engine.evaluate.flicker import run_flicker
from engine.evaluate.metrics import psnr, ssim
from engine.io.capture import load_capture
from engine.io.checkpoint import CHECKPOINT
from engine.scene.model import load_run, view_tensors
from engine.train import train

from . import report
from .micro import micro_decode, micro_freeze_step, micro_raster, warmup
from .report import fmt

VARIANTS = ("full", "rgb_only", "freeze", "early_stop", "cull")
# the skip variants are switches of the trainer (engine.train.config.TrainConfig, "skipping" block)
VARIANT_OVERRIDES = {"freeze": {"skip.freeze_static": True}, "early_stop": {"skip.early_stop": True},
                     "cull": {"skip.cull_frustum": True}}
CSV_FIELDS = ("preset", "variant", "wall_s", "step", "total_steps", "psnr", "ssim", "num_gaussians")


# ----------------------------------------------------------------------------- memory

def _status_kb(key: str) -> float | None:
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return float(line.split()[1])
    except OSError:
        return None
    return None


def reset_peak_rss() -> bool:
    """Reset the process's peak RSS (Linux >= 4.0). False when not possible."""
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def peak_rss_mb() -> tuple[float, str]:
    """(peak RSS in MiB, source): VmHWM since the last reset, else ru_maxrss (lifetime)."""
    hwm = _status_kb("VmHWM")
    if hwm is not None:
        return hwm / 1024.0, "VmHWM"
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return (r / 1024.0 / 1024.0 if platform.system() == "Darwin" else r / 1024.0), "ru_maxrss (process lifetime)"


def current_rss_mb() -> float:
    v = _status_kb("VmRSS")
    return float("nan") if v is None else v / 1024.0


# ----------------------------------------------------------------------------- eval helpers

def select_eval_frames(capture, stride: int = 1, exclude=()) -> list:
    frames = sorted(capture.eval_frames, key=lambda f: (f.camera, f.time))
    ex = {id(f) for f in exclude}
    frames = [f for f in frames if id(f) not in ex]
    return frames[:: max(1, int(stride))]


class FrameCache:
    """Ground-truth images of eval frames, loaded once."""

    def __init__(self):
        self._gt = {}

    def gt(self, frame) -> np.ndarray:
        key = str(frame.path)
        if key not in self._gt:
            self._gt[key] = frame.load_rgb()
        return self._gt[key]


def score_model(model, capture, frames, cache: FrameCache) -> dict:
    """PSNR / SSIM of a ``Model4D`` on ``frames`` (each at its own time)."""
    ps, ss = [], []
    was_training = model.training
    model.eval()
    with torch.no_grad():
        for f in frames:
            vt = view_tensors(capture.view(f), model.gaussians.means.device)
            rgb, _, _, _ = model.render(vt)
            pred = rgb[0].clamp(0, 1).detach().cpu().numpy()
            gt = cache.gt(f)
            ps.append(psnr(pred, gt))
            ss.append(ssim(pred, gt))
    model.train(was_training)
    return {"psnr": float(np.mean(ps)) if ps else float("nan"), "ssim": float(np.mean(ss)) if ss else float("nan")}


def score_checkpoint(path: Path, capture, frames, cache: FrameCache) -> dict:
    """Load one checkpoint file and score it; returns psnr, ssim, step, num_gaussians."""
    with tempfile.TemporaryDirectory(prefix="bt4d_bench_") as tmp:
        dst = Path(tmp) / CHECKPOINT
        try:
            os.link(path, dst)
        except OSError:
            shutil.copy2(path, dst)
        scene = load_run(tmp)
    out = score_model(scene.model, capture, frames, cache)
    out.update(step=scene.info.get("step"), total_steps=scene.info.get("total_steps"),
               num_gaussians=scene.num_gaussians)
    return out


# ----------------------------------------------------------------------------- one run

@dataclass
class RunResult:
    preset: str
    variant: str
    run_dir: str
    summary: dict
    curve: list
    final: dict
    peak_rss_mb: float
    rss_source: str
    wall_s: float
    extra: dict = field(default_factory=dict)


def _variant_kwargs(variant: str) -> dict:
    if variant not in VARIANTS:
        raise KeyError(f"unknown variant {variant!r}; choose from {', '.join(VARIANTS)}")
    return {"rgb_only": variant == "rgb_only"}


def variant_overrides(variant: str, overrides: dict | None = None) -> dict:
    """``overrides`` plus the variant's skip switch (an explicit override wins)."""
    ov = dict(VARIANT_OVERRIDES.get(variant, {}))
    ov.update(overrides or {})
    return ov


def run_one(capture, out_dir: Path, preset: str, variant: str, *, seconds: float, eval_every_s: float,
            eval_stride: int = 1, overrides: dict | None = None, seed: int = 0,
            train_fn: Callable | None = None, evaluate_fn: Callable | None = None, flicker: bool = True,
            bar_factory=None, device=None) -> RunResult:
    """Train one (preset, variant) for ``seconds`` and sample its error curve (module doc)."""
    train_fn = train_fn or train
    evaluate_fn = evaluate_fn or evaluate
    run_dir = Path(out_dir) / f"{preset}-{variant}"
    if run_dir.exists():
        shutil.rmtree(run_dir)
    snaps = run_dir / "snapshots"
    snaps.mkdir(parents=True)
    _variant_kwargs(variant)  # rejects unknown variants before anything is written
    ov = variant_overrides(variant, overrides)
    ov["checkpoint_every_s"] = float(eval_every_s)
    cache = FrameCache()
    curve_frames = select_eval_frames(capture, eval_stride)

    cancel = threading.Event()
    extra: dict = {}
    step_elapsed: dict[int, float] = {}
    seen = {"ino": None, "n": 0}
    bar = None
    ckpt = run_dir / CHECKPOINT

    def progress(p):
        nonlocal bar
        step_elapsed[int(p["step"])] = float(p["elapsed_s"])
        if bar is None and bar_factory is not None:
            bar = bar_factory(p["total_steps"], f"{preset}-{variant}")
        if bar is not None:
            bar.total = p["total_steps"]
            bar.update(p["step"] - bar.n)
            bar.set_postfix_str(f"psnr {p['psnr']:.2f} n={p['num_gaussians']}")
        try:
            st = ckpt.stat()
        except OSError:
            st = None
        if st is not None and st.st_ino != seen["ino"]:
            seen["ino"] = st.st_ino
            seen["n"] += 1
            dst = snaps / f"{seen['n']:04d}.pt"
            try:
                os.link(ckpt, dst)
            except OSError:
                shutil.copy2(ckpt, dst)

    reset_ok = reset_peak_rss()
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    summary = train_fn(capture, run_dir, preset=preset, seconds=seconds, resume=False, seed=seed,
                       progress=progress, cancel=cancel, overrides=ov, device=device,
                       **_variant_kwargs(variant))
    wall = time.perf_counter() - t0
    # process CPU seconds: on a shared machine a steadier measure of the work than wall time
    extra["cpu_s"] = round(time.process_time() - cpu0, 2)
    peak, src = peak_rss_mb()
    if not reset_ok:
        src += ", not reset between runs"
    if bar is not None:
        bar.close()
    # the final checkpoint is a snapshot too
    if ckpt.exists() and ckpt.stat().st_ino != seen["ino"]:
        seen["n"] += 1
        os.link(ckpt, snaps / f"{seen['n']:04d}.pt")

    curve = []
    for path in sorted(snaps.glob("*.pt")):
        try:
            s = score_checkpoint(path, capture, curve_frames, cache)
        except Exception as exc:  # a snapshot the trainer wrote half-way must not sink the bench
            extra.setdefault("snapshot_errors", []).append(f"{path.name}: {exc}")
            continue
        step = s.get("step")
        el = step_elapsed.get(int(step)) if step is not None else None
        if el is None and step is not None and step_elapsed:
            el = step_elapsed[min(step_elapsed, key=lambda k: abs(k - int(step)))]
        curve.append({"preset": preset, "variant": variant, "wall_s": el, "step": step,
                      "total_steps": s.get("total_steps"), "psnr": s["psnr"], "ssim": s["ssim"],
                      "num_gaussians": s["num_gaussians"]})
    curve.sort(key=lambda r: (r["step"] or 0))
    shutil.rmtree(snaps, ignore_errors=True)

    final = dict(evaluate_fn(run_dir, capture))
    skips = summary.get("skips") or {}
    if flicker:
        try:
            final["flicker"] = run_flicker(run_dir, capture)
        except Exception as exc:
            final["flicker"] = {"error": f"{type(exc).__name__}: {exc}"}
    for name in ("early_stop", "cull", "freeze"):  # what the trainer's skip switches did
        if skips.get(name) is not None:
            extra[name] = skips[name]
    if "budget_estimates" in summary:
        extra["budget_estimates"] = summary["budget_estimates"]
    return RunResult(preset, variant, str(run_dir), dict(summary), curve, final, round(peak, 1), src, wall, extra)


# ----------------------------------------------------------------------------- reporting

def write_csv(rows: list[dict], path: Path) -> Path:
    return report.write_csv(rows, path, CSV_FIELDS, digits=4)


def plot(results: list[RunResult], path: Path, title: str = "") -> Path:
    fig, axes = report.plt.subplots(1, 2, figsize=(11, 4.2))
    for r in results:
        pts = [c for c in r.curve if c["wall_s"] is not None and math.isfinite(c["psnr"])]
        if not pts:
            continue
        xs = [c["wall_s"] for c in pts]
        style = "--" if r.variant == "rgb_only" else "-"
        label = f"{r.preset} / {r.variant}"
        axes[0].plot(xs, [c["psnr"] for c in pts], style, marker="o", ms=3, label=label)
        axes[1].plot(xs, [c["ssim"] for c in pts], style, marker="o", ms=3, label=label)
    for ax, name in zip(axes, ("eval PSNR (dB)", "eval SSIM")):
        ax.set_xlabel("wall time since train() (s)")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    return report.save_figure(fig, path, title)


def time_to_within(curve: list, final_psnr: float, db: float = 0.5):
    for c in curve:
        if c["wall_s"] is not None and c["psnr"] >= final_psnr - db:
            return c["wall_s"]
    return None


def markdown(results: list[RunResult], micro: dict, meta: dict) -> str:
    lines = [f"# Error against wall time: {meta.get('capture')}", "",
             f"{meta.get('host')}, torch {torch.__version__}, {meta.get('threads')} threads; "
             + (f"budget {meta.get('seconds')} s per run" if meta.get("seconds") is not None
                else f"{(meta.get('overrides') or {}).get('iterations', 'preset')} steps per run")
             + f"; curve: eval frames every {meta.get('eval_stride')}, "
             f"checkpoint every {meta.get('eval_every_s')} s. Shared CPU: timings are noisy.", "",
             "| preset | variant | steps | train s | CPU s | PSNR | SSIM | LPIPS | PSNR inter | PSNR dyn | Gaussians | "
             "t to final-0.5 dB (s) | peak RSS MB | flicker x255 | notes |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        fin = r.final
        fl = fin.get("flicker") or {}
        notes = []
        if r.summary.get("status") != "finished":
            notes.append(r.summary.get("status"))
        if "early_stop" in r.extra and r.extra["early_stop"]["stopped_at"]:
            s = r.extra["early_stop"]["stopped_at"]
            notes.append(f"stopped at {s['step']}/{s['total_steps']}")
        if "cull" in r.extra:
            notes.append(f"culled {r.extra['cull']['pruned']}")
        if "freeze" in r.extra:
            fz = r.extra["freeze"]
            notes.append(f"frozen {fz['fraction_frozen'] * 100:.0f}% at end, woken {fz['woken']}")
        lines.append(
            f"| {r.preset} | {r.variant} | {r.summary.get('step')}/{r.summary.get('total_steps')} | "
            f"{fmt(r.summary.get('train_seconds'), 1)} | {fmt(r.extra.get('cpu_s'), 1)} | "
            f"{fmt(fin.get('psnr'))} | {fmt(fin.get('ssim'), 4)} | {fmt(fin.get('lpips'), 4)} | "
            f"{fmt(fin.get('psnr_interframe'))} | {fmt(fin.get('psnr_dynamic'))} | {fin.get('num_gaussians', '-')} | "
            f"{fmt(time_to_within(r.curve, fin.get('psnr') or float('nan')), 1)} | {fmt(r.peak_rss_mb, 0)} | "
            f"{fmt(fl.get('flicker_255'), 3)} | {'; '.join(notes)} |")
    if micro:
        lines += ["", "## Micro-benchmarks (same run)", ""]
        ra = micro.get("raster")
        if isinstance(ra, dict) and "small" in ra:
            s, d = ra["small"], ra["demo"]
            lines.append(f"- rasterizer fwd+bwd, {s['size']}, {s['gaussians']} Gaussians: cpu {s['cpu_ms']:.1f} ms vs "
                         f"dense reference {s['reference_ms']:.1f} ms -> **{s['speedup_vs_reference']:.1f}x**")
            lines.append(f"- rasterizer fwd+bwd, {d['size']}, {d['gaussians']} Gaussians: cpu {d['cpu_ms']:.1f} ms vs "
                         f"plain-PyTorch tiled {d['torch_ms']:.1f} ms -> **{d['speedup_vs_torch']:.1f}x**")
        elif ra:
            lines.append(f"- rasterizer: {ra}")
        fz = micro.get("freeze_step")
        if isinstance(fz, dict) and "speedup" in fz:
            lines.append(f"- deformation + raster fwd+bwd of one train view with {fz['frozen_fraction'] * 100:.0f}% of "
                         f"{fz['gaussians']} Gaussians frozen: {fz['step_ms_frozen']:.0f} ms vs "
                         f"{fz['step_ms_unfrozen']:.0f} ms "
                         f"unfrozen -> **{fz['speedup']:.2f}x** (interleaved A/B medians)")
        de = micro.get("decode")
        if isinstance(de, dict) and "speedup_vs_community" in de:
            lines.append(f"- spike decode, {de['frames']} frames {de['size']}: "
                         f"read_spikes {de['read_spikes_s'] * 1e3:.1f} ms ({de['mb_per_s']:.0f} MB/s) -> "
                         f"**{de['speedup_vs_community']:.1f}x** the community per-frame "
                         f"loader, **{de['speedup_vs_python_loop']:.0f}x** the per-byte Python loop "
                         f"(identical output: {de['identical']})")
        elif de:
            lines.append(f"- spike decode: {de}")
    lines += ["", f"Peak RSS source: {results[0].rss_source if results else '-'}."]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- suite

def run_bench(capture, out_dir, *, presets=("fast",), variants=("full", "rgb_only"), seconds: float = 60.0,
              eval_every_s: float = 10.0, eval_stride: int = 1, overrides: dict | None = None, seed: int = 0,
              micro: bool = True, quick: bool = False, progress: bool = True, train_fn=None, evaluate_fn=None,
              flicker: bool = True, device=None, log=print) -> dict:
    """Run every (preset, variant), the micro-benchmarks, and write CSV / PNG / markdown / JSON."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cap = load_capture(capture) if not hasattr(capture, "eval_frames") else capture
    bar_factory = None
    if progress:
        def bar_factory(total, desc):
            return tqdm(total=total, desc=desc, unit="step", dynamic_ncols=True, leave=True)
    warm_s = warmup()
    results: list[RunResult] = []
    for preset in presets:
        for variant in variants:
            r = run_one(cap, out, preset, variant, seconds=seconds, eval_every_s=eval_every_s,
                        eval_stride=eval_stride, overrides=overrides, seed=seed, train_fn=train_fn,
                        evaluate_fn=evaluate_fn, flicker=flicker, bar_factory=bar_factory, device=device)
            results.append(r)
            if log:
                log(f"{preset}-{variant}: psnr {fmt(r.final.get('psnr'))} ssim {fmt(r.final.get('ssim'), 4)} "
                    f"steps {r.summary.get('step')} in {fmt(r.summary.get('train_seconds'), 1)} s "
                    f"({fmt(r.extra.get('cpu_s'), 1)} CPU s), "
                    f"peak RSS {r.peak_rss_mb:.0f} MB")
    micro_res = {}
    frozen_runs = [r for r in results if r.variant == "freeze"]
    if micro and frozen_runs:
        try:
            micro_res["freeze_step"] = micro_freeze_step(frozen_runs[0].run_dir, cap)
        except Exception as exc:
            micro_res["freeze_step"] = {"error": f"{type(exc).__name__}: {exc}"}
    if micro:
        for name, fn in (("raster", micro_raster), ("decode", micro_decode)):
            try:
                micro_res[name] = fn(quick=quick)
            except Exception as exc:
                micro_res[name] = {"error": f"{type(exc).__name__}: {exc}"}
    meta = {"capture": str(getattr(cap, "root", capture)), "host": platform.node(), "threads": torch.get_num_threads(),
            "seconds": seconds, "eval_every_s": eval_every_s, "eval_stride": eval_stride,
            "presets": list(presets), "variants": list(variants), "overrides": overrides or {},
            "warmup_s": round(warm_s, 2)}
    rows = [c for r in results for c in r.curve]
    write_csv(rows, out / "bench.csv")
    plot(results, out / "bench.png", title=f"{Path(meta['capture']).name}: eval error against wall time")
    md = markdown(results, micro_res, meta)
    (out / "bench.md").write_text(md, encoding="utf-8")
    data = {"meta": meta, "micro": micro_res,
            "runs": [{"preset": r.preset, "variant": r.variant, "run_dir": r.run_dir, "summary": r.summary,
                      "final": r.final, "curve": r.curve, "peak_rss_mb": r.peak_rss_mb, "rss_source": r.rss_source,
                      "wall_s": r.wall_s, "extra": r.extra} for r in results]}
    (out / "bench.json").write_text(json.dumps(data, indent=2, default=_json_default), encoding="utf-8")
    return {"results": results, "micro": micro_res, "markdown": md, "out": str(out)}


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, torch.Tensor):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    return str(o)

