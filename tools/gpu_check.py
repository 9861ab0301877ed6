"""``python -m tools gpu-check``: the gsplat (CUDA) rasterizer against our CPU path.

Run on a machine with a GPU (CI has none: this is not a unit test). It prints

1. the environment: torch, CUDA device, gsplat version, and what ``backend="auto"``
   resolves to for CUDA and CPU tensors;
2. parity: bench-raster's random scenes (RGB and SH degree 3) rendered by gsplat on the
   GPU and by the ``cpu`` backend: max |diff| of colours, alphas and expected depth, and
   the cosine between the two backends' gradients of each parameter for one loss;
3. speed: forward and forward+backward median wall ms of both backends per cell
   (synchronised), and their ratio, up to the RGB cameras' 1080x720.

Exit status 1 when CUDA or gsplat is unusable or a parity bound is broken. The bounds are
loose on purpose: gsplat caps alpha at its own 0.999 where we cap at 0.99, and its
``eps2d`` blur and culling differ in the last bits.
"""
from __future__ import annotations

import statistics
import time

import torch

from engine.raster import gsplat_backend, rasterization, resolve_backend

from .bench_raster import make_scene

HELP = "check the gsplat (CUDA) rasterizer against the CPU path: parity and speed"

PARAMS = ("means", "quats", "scales", "opacities", "colors")
COLOUR_ATOL = 2e-2   # the alpha caps differ: 0.99 (ours) vs 0.999 (gsplat)
GRAD_COS_MIN = 0.95


def add_arguments(parser) -> None:
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per cell (median)")
    parser.add_argument("--sizes", default="160x120,320x240,1080x720", help="comma list WxH")
    parser.add_argument("--counts", default="10000,50000,200000", help="comma list of Gaussian counts")
    parser.add_argument("--skip-cpu-above", type=int, default=50_000,
                        help="time the cpu backend only up to this many Gaussians (it is slow)")


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _run(args, device, backend, width, height, sh_degree, grads=True):
    """One forward (+ backward of a fixed loss); returns outputs and the leaf gradients."""
    params = [a.detach().to(device).clone().requires_grad_(grads) for a in args[:5]]
    vm, K = args[5].to(device), args[6].to(device)
    colors, alphas, meta = rasterization(*params, vm, K, width, height, sh_degree=sh_degree,
                                         backend=backend)
    out = {"colors": colors, "alphas": alphas, "depths": meta["depths"], "backend": meta["backend"]}
    if grads:
        w = torch.linspace(0.5, 1.5, width, device=device)  # a loss that is not a plain sum
        (colors.mean(-1) * w).sum().add(0.3 * alphas.sum()).add(0.1 * meta["depths"].sum()).backward()
        out["grads"] = {k: p.grad.detach().cpu() for k, p in zip(PARAMS, params)}
    return out


def parity(width, height, n, sh_degree) -> bool:
    sc = make_scene(n, width, height, seed=3, sh_degree=sh_degree)
    gs = _run(sc, torch.device("cuda"), "gsplat", width, height, sh_degree)
    cp = _run(sc, torch.device("cpu"), "cpu", width, height, sh_degree)
    ok = gs["backend"] == "gsplat"
    line = f"  parity {width}x{height} N={n} sh={sh_degree}: backend {gs['backend']}"
    for k in ("colors", "alphas", "depths"):
        d = (gs[k].detach().cpu() - cp[k].detach()).abs()
        # depth is in metres and follows alpha: compare it where both are opaque enough
        if k == "depths":
            both = (gs["alphas"].detach().cpu() > 0.5) & (cp["alphas"].detach() > 0.5)
            d = d[both] / cp[k].detach()[both].clamp_min(1e-6)  # relative
        worst = float(d.max()) if d.numel() else 0.0
        bound = COLOUR_ATOL if k != "depths" else 0.05
        ok &= worst <= bound
        line += f"; {k} max|d| {worst:.1e}{'' if k != 'depths' else ' (rel)'}"
    cos = {}
    for k in PARAMS:
        a, b = gs["grads"][k].reshape(-1), cp["grads"][k].reshape(-1)
        cos[k] = float(torch.nn.functional.cosine_similarity(a, b, dim=0))
        ok &= cos[k] > GRAD_COS_MIN
    line += "; grad cos " + " ".join(f"{k} {v:.6f}" for k, v in cos.items())
    print(line + ("" if ok else "   <-- FAIL"), flush=True)
    return ok


def time_cell(sc, device, backend, width, height, repeats):
    def once(grads):
        t0 = time.perf_counter()
        if grads:
            _run(sc, device, backend, width, height, None)
        else:
            with torch.no_grad():
                _run(sc, device, backend, width, height, None, grads=False)
        _sync(device)
        return time.perf_counter() - t0

    once(True)  # warm-up
    f = statistics.median(once(False) for _ in range(repeats))
    fb = statistics.median(once(True) for _ in range(repeats))
    return 1e3 * f, 1e3 * fb


def main(args) -> int:
    print(f"torch {torch.__version__}; CUDA available: {torch.cuda.is_available()}", flush=True)
    if not torch.cuda.is_available():
        print("no CUDA device: nothing to check")
        return 1
    print(f"device: {torch.cuda.get_device_name(0)}; CUDA {torch.version.cuda}")
    t0 = time.perf_counter()
    ok = gsplat_backend.available()
    print(f"gsplat usable: {ok} ({time.perf_counter() - t0:.1f} s to load"
          f"{'' if ok else ': ' + gsplat_backend.unavailable_reason()})", flush=True)
    if not ok:
        return 1
    import gsplat  # lazy: only here, after available() said it loads

    print(f"gsplat {gsplat.__version__}; auto resolves to {resolve_backend('auto', torch.device('cuda'))!r} "
          f"on CUDA tensors, {resolve_backend('auto', torch.device('cpu'))!r} on CPU tensors")
    good = True
    for sh in (None, 3):
        for (w, h, n) in ((64, 48, 300), (320, 240, 5000)):
            good &= parity(w, h, n, sh)

    sizes = [tuple(int(v) for v in s.lower().split("x")) for s in args.sizes.split(",") if s]
    counts = [int(v) for v in args.counts.split(",") if v]
    print("\n| size | N | gsplat fwd ms | gsplat fwd+bwd ms | cpu fwd ms | cpu fwd+bwd ms | cpu/gsplat fwd+bwd |")
    print("|---|---|---|---|---|---|---|")
    for (w, h) in sizes:
        for n in counts:
            sc = make_scene(n, w, h)
            gf, gfb = time_cell(sc, torch.device("cuda"), "gsplat", w, h, args.repeats)
            if n <= args.skip_cpu_above:
                cf, cfb = time_cell(sc, torch.device("cpu"), "cpu", w, h, max(1, args.repeats // 2))
                tail = f" {cf:.1f} | {cfb:.1f} | {cfb / gfb:.0f}x |"
            else:
                tail = " - | - | - |"
            print(f"| {w}x{h} | {n} | {gf:.2f} | {gfb:.2f} |" + tail, flush=True)
    print("\nparity:", "ok" if good else "FAILED")
    return 0 if good else 1
