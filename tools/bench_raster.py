"""``python -m tools bench-raster``: rasterizer speed, fast CPU path vs plain PyTorch.

Random scene in front of one camera (Gaussians a few to tens of pixels across), forward
and forward+backward wall time (median of repeats) at 160x120 and 320x240 with
2k/10k/50k Gaussians. Backends: ``cpu`` (numba kernels), ``torch`` (the tiled
plain-PyTorch autograd path: the baseline), ``reference`` (dense, only where it fits).
Timings on a shared machine are noisy: the load average is printed with the table.
"""
from __future__ import annotations

import math
import os
import statistics
import tempfile
import time

import torch

from engine.raster import cpu as raster_cpu
from engine.raster import rasterization

HELP = "benchmark the Gaussian rasterizer (fast CPU path vs plain PyTorch)"

SIZES = [(160, 120), (320, 240)]
COUNTS = [2_000, 10_000, 50_000]
DENSE_LIMIT = 4_000_000  # pixels x Gaussians for the dense reference


def add_arguments(parser) -> None:
    parser.add_argument("--quick", action="store_true", help="160x120 only, 2k/10k, 2 repeats")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per cell (median)")
    parser.add_argument("--backends", default="cpu,torch,reference",
                        help="comma list among cpu,torch,reference (default: all)")
    parser.add_argument("--threads", type=int, default=0,
                        help="torch / numba threads (default: leave as is)")
    parser.add_argument("--cold-compile", action="store_true",
                        help="use an empty numba cache dir to time a cold JIT compile")
    parser.add_argument("--sh-degree", type=int, default=None, help="colours as SH of this degree")
    parser.add_argument("--size", default=None, help="only this image size, e.g. 320x240")
    parser.add_argument("--breakdown", action="store_true",
                        help="also time each stage of the cpu forward+backward (wall and CPU "
                             "time: projection, binning, depth sort, pack, compositing, "
                             "gradient scatter, torch glue)")
    parser.add_argument("--counts", default=None,
                        help="comma list of Gaussian counts (default 2000,10000,50000)")


def make_scene(n, width, height, seed=0, sh_degree=None):
    g = torch.Generator().manual_seed(seed)
    f = 0.9 * width
    z = 2.0 + 4.0 * torch.rand(n, generator=g)
    x = (torch.rand(n, generator=g) * 2 - 1) * z * (width / 2) / f * 1.1
    y = (torch.rand(n, generator=g) * 2 - 1) * z * (height / 2) / f * 1.1
    means = torch.stack([x, y, z], -1)
    quats = torch.randn(n, 4, generator=g)
    # world sigma ~1.2 cm at 2-6 m: ~1-3 px sigma at 320x240, i.e. boxes of 5-25 px
    scales = torch.exp(torch.randn(n, 3, generator=g) * 0.4 + math.log(0.012 * width / 320))
    opac = torch.sigmoid(torch.randn(n, generator=g) * 1.5)
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=g)
    else:
        colors = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g) * 0.2
    viewmats = torch.eye(4)[None]
    Ks = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])[None]
    return [means, quats, scales, opac, colors, viewmats, Ks]


def time_cell(args, width, height, backend, repeats, sh_degree, with_cpu=False):
    """Median ms of forward and forward+backward (wall), first-call seconds, and with
    ``with_cpu`` the median process CPU ms of forward+backward (all threads: on a shared
    machine the steadier measure of the work done)."""
    params = [a.clone().requires_grad_(True) for a in args[:5]]

    def fwd():
        return rasterization(*params, args[5], args[6], width, height, sh_degree=sh_degree,
                             backend=backend)

    def fwd_bwd():
        c, a, m = fwd()
        m["means2d"].retain_grad()
        (c.sum() + 0.5 * a.sum() + 0.1 * m["depths"].sum()).backward()
        for p in params:
            p.grad = None

    t0 = time.perf_counter()
    fwd_bwd()  # warm-up (JIT compile / cache load on the first cell)
    first = time.perf_counter() - t0
    tf, tb, cb = [], [], []
    for _ in range(repeats):
        with torch.no_grad():
            t0 = time.perf_counter()
            fwd()
            tf.append(time.perf_counter() - t0)
        c0 = time.process_time()
        t0 = time.perf_counter()
        fwd_bwd()
        tb.append(time.perf_counter() - t0)
        cb.append(time.process_time() - c0)

    def med(v):
        return 1e3 * statistics.median(v) if v else float("nan")

    if with_cpu:
        return med(tf), med(tb), first, med(cb)
    return med(tf), med(tb), first


def _maxrss_mb() -> float:
    try:
        import resource  # lazy: Unix only

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    except Exception:  # not on Windows
        return float("nan")


def main(args) -> int:
    if args.cold_compile:
        os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="bt4d-numba-")
    if args.threads > 0:
        torch.set_num_threads(args.threads)
        os.environ.setdefault("NUMBA_NUM_THREADS", str(args.threads))

    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    sizes = SIZES[:1] if args.quick else SIZES
    if args.size:
        w, h = (int(v) for v in args.size.lower().split("x"))
        sizes = [(w, h)]
    counts = COUNTS[:2] if args.quick else COUNTS
    if args.counts:
        counts = [int(v) for v in args.counts.split(",") if v.strip()]
    repeats = 2 if args.quick else max(1, args.repeats)

    if "cpu" in backends:
        if not raster_cpu.available():
            print("numba unavailable:", raster_cpu.unavailable_reason(), "- skipping cpu")
            backends.remove("cpu")
        else:
            import numba  # lazy: after NUMBA_CACHE_DIR / NUMBA_NUM_THREADS are set above

            print(f"numba {numba.__version__}, {numba.get_num_threads()} threads; "
                  f"torch {torch.__version__}, {torch.get_num_threads()} threads; "
                  f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}")
            # first call in this process: JIT compile, or load from numba's cache
            sc = make_scene(500, 64, 48, sh_degree=args.sh_degree)
            _, _, first = time_cell(sc, 64, 48, "cpu", 0, args.sh_degree)
            try:
                layer = numba.threading_layer()
            except Exception:
                layer = "?"
            print(f"first cpu call (compile{' cold' if args.cold_compile else ' or cache load'}): "
                  f"{first:.2f} s  [threading layer: {layer}]")
    load0 = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print(f"load average at start: {load0[0]:.2f} (cores: {os.cpu_count()})")

    rows = []
    cpu_ms = {}
    peaks = {}
    for backend in backends:
        for (w, h) in sizes:
            for n in counts:
                if backend == "reference" and w * h * n > DENSE_LIMIT:
                    rows.append((backend, w, h, n, None, None))
                    continue
                sc = make_scene(n, w, h, sh_degree=args.sh_degree)
                f, fb, _, cfb = time_cell(sc, w, h, backend, repeats, args.sh_degree, with_cpu=True)
                rows.append((backend, w, h, n, f, fb))
                cpu_ms[(backend, w, h, n)] = cfb
                print(f"  {backend:9s} {w}x{h} N={n:>6d}: fwd {f:8.1f} ms  fwd+bwd {fb:8.1f} ms"
                      f"  (fwd+bwd CPU {cfb:8.1f} ms)", flush=True)
        peaks[backend] = _maxrss_mb()
    load1 = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3

    print()
    print("| size | N | " + " | ".join(f"{b} fwd ms | {b} fwd+bwd ms" for b in backends)
          + (" | torch/cpu fwd+bwd | torch/cpu fwd+bwd CPU time |" if "cpu" in backends and "torch" in backends
             else " |"))
    print("|---|---|" + "---|---|" * len(backends)
          + ("---|---|" if "cpu" in backends and "torch" in backends else ""))
    cells = {(b, w, h, n): (f, fb) for b, w, h, n, f, fb in rows}
    for (w, h) in sizes:
        for n in counts:
            line = f"| {w}x{h} | {n} |"
            for b in backends:
                f, fb = cells[(b, w, h, n)]
                line += " - | - |" if f is None else f" {f:.1f} | {fb:.1f} |"
            if "cpu" in backends and "torch" in backends:
                c_fb, t_fb = cells[("cpu", w, h, n)][1], cells[("torch", w, h, n)][1]
                line += f" {t_fb / c_fb:.1f}x |" if c_fb and t_fb else " - |"
                c_c, t_c = cpu_ms.get(("cpu", w, h, n)), cpu_ms.get(("torch", w, h, n))
                line += f" {t_c / c_c:.1f}x |" if c_c and t_c else " - |"
            print(line)
    print()
    print("peak RSS after each backend (MB, cumulative): "
          + ", ".join(f"{b} {v:.0f}" for b, v in peaks.items()))
    print(f"load average start/end: {load0[0]:.2f} / {load1[0]:.2f}; "
          f"reference = dense, only where pixels x N <= {DENSE_LIMIT:.0e}; torch = tiled "
          f"plain-PyTorch autograd baseline")
    if args.breakdown and "cpu" in backends:
        from . import raster_breakdown  # lazy: only with --breakdown

        raster_breakdown.run(make_scene, sizes, counts, repeats, sh_degree=args.sh_degree)
        load2 = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
        print(f"load average after the breakdown: {load2[0]:.2f}")
    return 0
