"""``python -m engine train CAPTURE --out RUN``: train a 4D Gaussian scene (tqdm progress)."""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading

from tqdm import tqdm

from ..errors import CaptureError, RunError
from ..train import train
from ..train.config import DEFAULT_PRESET, PRESETS

HELP = "train a 4D Gaussian scene on a capture folder"


_BOOLS = {"true": True, "yes": True, "on": True, "false": False, "no": False, "off": False}


def parse_overrides(items) -> dict:
    """``key=value`` strings -> dict (values parsed as JSON when possible; true/false,
    yes/no, on/off in any case are booleans, so ``--set early_stop=False`` is off)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise SystemExit(f"--set expects key=value, got {item!r}")
        k, v = item.split("=", 1)
        if v.strip().lower() in _BOOLS:
            out[k.strip()] = _BOOLS[v.strip().lower()]
            continue
        try:
            out[k.strip()] = json.loads(v)
        except ValueError:
            out[k.strip()] = v
    return out


SKIP_HELP = """\
settings: --set GROUP.FIELD=VALUE (repeatable), e.g. --set densify.max_gaussians=40000; the groups
are schedule, init, gaussians, densify, motion, hexplane, births, losses, skip, spike, spike_flow,
baseline (every name: python -c 'from engine.train.config import setting_names; print(setting_names())');
the flat names of older versions (--set iterations=500) still work.

skipping what a scene does not need (all off by default):
  skip.freeze_static=true  freeze Gaussians that do not move (CPOStream): they skip the
                           deformation field; tune skip.freeze_k_checks, skip.freeze_motion_eps_px
  skip.early_stop=true     stop when the PSNR on a few train frames held back from training
                           stops improving (never the eval frames); tune skip.early_stop_patience
  skip.cull_frustum=true   prune Gaussians outside every train camera's frustum"""


def add_arguments(p) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = SKIP_HELP
    p.add_argument("capture", help="capture folder (transforms.json)")
    p.add_argument("--out", required=True, help="run directory (checkpoint, run.json, metrics)")
    p.add_argument("--preset", default=DEFAULT_PRESET, choices=list(PRESETS),
                   help=f"{DEFAULT_PRESET} (default: what every published figure uses), " + ", ".join(PRESETS[1:]))
    p.add_argument("--seconds", type=float, default=None, help="wall-clock budget; the schedule is sized to fit")
    p.add_argument("--rgb-only", action="store_true", help="ignore spike streams")
    p.add_argument("--restart", action="store_true", help="start over instead of resuming RUN/checkpoint.pt")
    p.add_argument("--device", default="auto", help="auto (default: CUDA when available), cpu, cuda, cuda:1")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE",
                   help="change a setting, e.g. --set schedule.iterations=500 (repeatable; see below)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def main(args) -> int:
    overrides = parse_overrides(args.overrides)
    from ..train.config import get_preset

    try:  # a wrong name or value is reported now, before the capture loads and kernels compile
        get_preset(args.preset, overrides)
    except (KeyError, ValueError) as exc:
        print(f"error: {exc.args[0] if exc.args else exc}", file=sys.stderr)
        return 2
    cancel = threading.Event()
    bar = None

    def progress(d):
        nonlocal bar
        if args.quiet:
            return
        if bar is None:
            bar = tqdm(total=d["total_steps"], initial=d["step"] - 1, unit="step", dynamic_ncols=True, file=sys.stderr)
        if bar.total != d["total_steps"]:
            bar.total = d["total_steps"]
        bar.update(d["step"] - bar.n)
        bar.set_postfix(stage=d["stage"], loss=f"{d['loss']:.4f}", psnr=f"{d['psnr']:.2f}",
                        gaussians=d["num_gaussians"], refresh=False)

    def on_sigint(signum, frame):  # first Ctrl-C: checkpoint and stop cleanly
        cancel.set()

    old = signal.signal(signal.SIGINT, on_sigint)
    try:
        summary = train(args.capture, args.out, preset=args.preset, seconds=args.seconds, rgb_only=args.rgb_only,
                        resume=not args.restart, device=args.device, seed=args.seed, progress=progress,
                        cancel=cancel, overrides=overrides,
                        on_stage=None if args.quiet else lambda text: print(f"{text}...", file=sys.stderr, flush=True))
    except (CaptureError, RunError, KeyError, ValueError) as exc:
        if bar is not None:
            bar.close()
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        signal.signal(signal.SIGINT, old)
    if bar is not None:
        bar.close()
    note = ended_note(summary)
    if note and not args.quiet:
        print(note, file=sys.stderr)
    print(json.dumps(summary, indent=2))
    return 0 if summary["status"] in ("finished", "cancelled") else 1


def ended_note(summary: dict) -> str | None:
    """One line for a budget run that did not use its time (it converged) or that spent most
    of it preparing (stereo, initial Gaussians; run.json ``budget_estimates.preparation_heavy``), else None."""
    used, steps = summary.get("budget_used"), summary.get("step")
    est = summary.get("budget_estimates") or {}
    if est.get("preparation_heavy") and summary.get("ended_by") == "budget":
        return (f"warning: preparing the capture took {est['preparation_s']:.0f} s, "
                f"{est['preparation_share']:.0%} of the --seconds budget; {steps} steps trained in what was left: "
                "give --seconds well above the preparation time")
    if summary.get("ended_by") == "converged" and used is not None:
        return f"note: converged after {steps} steps, {used:.0%} of the budget ({converged_why(summary)})"
    return None


def converged_why(summary: dict) -> str:
    """What said a run converged, in a few words (the command line's note, the Blender panel's message)."""
    settle = summary.get("settle") or {}
    if settle.get("converged_at") is not None:
        return (f"the schedule ended at step {settle['from_step']}; the train frames then stopped improving, "
                "and more steps would not sharpen the new view")
    return "held-back train frames stopped improving"
