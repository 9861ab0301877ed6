"""Where a run loses static pixels against another: in front of the true surface, or on it.

    python -m tools static-error CAP RUN_A RUN_B [--front 0.05] [--images DIR]

Issue 47 asks which part of the model repaints what never moves: a colour (the spike loss's
luminance reaching a Gaussian's colour) or a place (a Gaussian sitting in space the eval camera
looks through). The two look alike in PSNR and apart in depth. For each eval camera, over the
static pixels (``engine.evaluate.metrics.static_mask``: ground truth within 0.03 of its median in
every frame) with a ground-truth depth, at the RGB instants and between them, each pixel is put in
one class by RUN_B's rendered depth ``d`` against the truth ``D``: *front* (``d < (1 - front) D``:
something renders in front of the surface), *behind* (``d > (1 + front) D``) or *surface*. Printed
per camera and instant kind: both runs' static PSNR, the share of RUN_B's extra squared error (B - A)
in each class, and RUN_B's and RUN_A's mean colour error (render - truth, R G B) on the surface class.
A share above 1 in one class and below 0 in another: B wins there and loses more here.
``--images DIR``: B - A's static error per camera (red: B worse, blue: B better; the rest dimmed).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from engine.errors import CaptureError  # noqa: E402
from engine.evaluate.metrics import is_interframe, static_mask  # noqa: E402
from engine.io.capture import load_capture  # noqa: E402
from engine.scene.model import load_run  # noqa: E402

CLASSES = ("front", "surface", "behind")
KINDS = ("inst", "between")


def depth_classes(depth: np.ndarray, true_depth: np.ndarray, front: float) -> dict:
    """{class: bool [H, W]} of a rendered depth against the true one; pixels without a finite
    positive true depth are in none."""
    d, t = np.asarray(depth, np.float64), np.asarray(true_depth, np.float64)
    valid = np.isfinite(t) & (t > 0)
    ahead = valid & (d < (1.0 - front) * t)
    back = valid & (d > (1.0 + front) * t)
    return {"front": ahead, "surface": valid & ~ahead & ~back, "behind": back}


class Accumulator:
    """Squared error (mean over RGB) and colour error sums per (camera, kind, class)."""

    def __init__(self):
        self.sse: dict = {}
        self.bias: dict = {}
        self.n: dict = {}

    def add(self, key, err: np.ndarray, diff: np.ndarray, mask: np.ndarray) -> None:
        self.sse[key] = self.sse.get(key, 0.0) + float(err[mask].sum())
        self.bias[key] = self.bias.get(key, np.zeros(3)) + diff[mask].sum(0)
        self.n[key] = self.n.get(key, 0) + int(mask.sum())


def static_frames(cap) -> list[tuple]:
    """(camera, frame, ground truth, static mask, "inst" | "between") per eval frame, each camera's in
    time order: loaded once and scored for both runs."""
    rgb_times = sorted({float(f.time) for f in cap.frames})
    eval_cams = {f.camera for f in cap.eval_frames}
    out = []
    for cam, fs in cap.frames_by_camera().items():
        if cam not in eval_cams:
            continue
        gts = [fr.load_rgb() for fr in fs]
        still = static_mask(gts)
        out += [(cam, fr, gt, still, "between" if is_interframe(float(fr.time), rgb_times) else "inst")
                for fr, gt in zip(fs, gts)]
    return out


def score(run, cap, frames, classes=None, front: float = 0.05, keep_maps: bool = False):
    """(Accumulator over ``run``'s static pixels of ``frames`` (:func:`static_frames`) split by depth
    class, the class dicts per frame, per-camera mean static error maps or None). ``classes``: one
    class dict per frame to use (another run's); None: this run's own, from its rendered depth."""
    scene = load_run(run, device="cpu")
    acc, used, maps = Accumulator(), [], {}
    for i, (cam, fr, gt, still, kind) in enumerate(frames):
        out = scene.render([cap.view(fr)])[0]
        diff = np.asarray(out["rgb"], np.float64)[..., :3] - np.asarray(gt, np.float64)[..., :3]
        err = (diff ** 2).mean(-1)
        cls = depth_classes(out["depth"], fr.load_depth(), front) if classes is None else classes[i]
        used.append(cls)
        for c, m in cls.items():
            acc.add((cam, kind, c), err, diff, m & still)
        acc.add((cam, kind, "all"), err, diff, still)
        if keep_maps:
            s, k = maps.get(cam, (np.zeros_like(err), 0))
            maps[cam] = (s + np.where(still, err, np.nan), k + 1)
    return acc, used, {c: s / k for c, (s, k) in maps.items()} if keep_maps else None


def psnr_of(acc: Accumulator, key) -> float:
    n = acc.n.get(key, 0)
    return float("nan") if n == 0 else -10.0 * np.log10(max(acc.sse[key] / n, 1e-12))


def rows(acc_a: Accumulator, acc_b: Accumulator) -> list[dict]:
    """One row per (camera, kind): both PSNRs, the class shares of B's extra error, surface biases."""
    out = []
    for cam, kind in sorted({k[:2] for k in acc_b.n}, key=lambda k: (k[0], KINDS.index(k[1]))):
        extra = acc_b.sse.get((cam, kind, "all"), 0.0) - acc_a.sse.get((cam, kind, "all"), 0.0)
        shares = {c: (acc_b.sse.get((cam, kind, c), 0.0) - acc_a.sse.get((cam, kind, c), 0.0)) / extra
                  if extra != 0 else float("nan") for c in CLASSES}
        surf = (cam, kind, "surface")
        bias = {r: acc.bias[surf] / max(acc.n[surf], 1) if surf in acc.n else np.full(3, np.nan)
                for r, acc in (("a", acc_a), ("b", acc_b))}
        out.append({"camera": cam, "kind": kind, "psnr_a": psnr_of(acc_a, (cam, kind, "all")),
                    "psnr_b": psnr_of(acc_b, (cam, kind, "all")), "shares": shares,
                    "front_px": acc_b.n.get((cam, kind, "front"), 0) / max(acc_b.n.get((cam, kind, "all"), 1), 1),
                    "bias_a": bias["a"], "bias_b": bias["b"]})
    return out


def markdown(table: list[dict]) -> str:
    head = ("| camera | instants | static PSNR A | static PSNR B | B's static px in front | extra error: front / "
            "surface / behind | colour error on the surface, B (R G B) | A (R G B) |")
    lines = [head, "|---|---|---|---|---|---|---|---|"]
    for r in table:
        sh = " / ".join(f"{r['shares'][c]:+.2f}" for c in CLASSES)
        ba, bb = (" ".join(f"{v:+.4f}" for v in r[k]) for k in ("bias_a", "bias_b"))
        lines.append(f"| {r['camera']} | {r['kind']} | {r['psnr_a']:.2f} | {r['psnr_b']:.2f} | "
                     f"{100 * r['front_px']:.1f}% | {sh} | {bb} | {ba} |")
    return "\n".join(lines)


def write_maps(maps_a: dict, maps_b: dict, out_dir: Path) -> list[Path]:
    """B - A's mean static error per camera as PNGs (red: B worse, blue: B better)."""
    import cv2

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for cam, eb in maps_b.items():
        d = eb - maps_a[cam]
        still = np.isfinite(d)
        scale = np.percentile(np.abs(d[still]), 99.5) if still.any() else 1.0
        v = np.clip(np.nan_to_num(d) / max(scale, 1e-12), -1.0, 1.0)
        img = np.zeros(d.shape + (3,), np.float32)
        img[..., 2], img[..., 0] = np.maximum(v, 0), np.maximum(-v, 0)  # BGR: red where B is worse
        img[~still] = 0.15
        path = out_dir / f"static_error_{cam}.png"
        cv2.imwrite(str(path), (img * 255).astype(np.uint8))
        paths.append(path)
    return paths


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture")
    ap.add_argument("run_a", help="the reference run (e.g. RGB-only)")
    ap.add_argument("run_b", help="the run whose static pixels are explained (e.g. the full model)")
    ap.add_argument("--front", type=float, default=0.05, help="relative depth margin of the front / behind classes")
    ap.add_argument("--images", type=Path, default=None, help="write B - A's static error maps here")
    args = ap.parse_args(argv)
    cap = load_capture(args.capture)
    missing = [f for f in cap.eval_frames if getattr(f, "depth_file_path", None) is None]
    if not cap.eval_frames or missing:
        where = missing[0].path if missing else args.capture
        raise SystemExit(str(CaptureError(where, "static-error needs eval frames with ground-truth depth "
                                                 "(make_capture.py --depth)")))
    frames = static_frames(cap)
    acc_b, classes, maps_b = score(args.run_b, cap, frames, front=args.front, keep_maps=args.images is not None)
    acc_a, _, maps_a = score(args.run_a, cap, frames, classes=classes, keep_maps=args.images is not None)
    print(f"A = {args.run_a}\nB = {args.run_b}\n{markdown(rows(acc_a, acc_b))}")
    if args.images is not None:
        for p in write_maps(maps_a, maps_b, args.images):
            print(f"wrote {p}")


if __name__ == "__main__":
    main()
