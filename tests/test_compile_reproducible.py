"""The numba kernels give the same bits when compiled in this process as when loaded from
numba's cache by a later one (docs/experiments/rasterizer.md "Reproducible across numba's cache").

Found in issue 13's review: with ``fastmath`` "reassoc" in the rasterizer's backward tile
kernel, a process that compiled ``rasterize_bwd`` got other gradients than every later
process that loaded it from the cache, so a user's first run on a machine trained a
different model (demo, 200 steps: 23,943 against 24,305 Gaussians) and a run resumed in a
new process did not continue the same computation."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _probe(cache: Path) -> str:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    out = subprocess.run([sys.executable, str(Path(__file__).with_name("compile_probe.py")), str(ROOT)],
                         env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.strip().splitlines()[-1]


def test_a_cold_compile_and_a_cache_load_give_the_same_bits(tmp_path):
    cache = tmp_path / "numba"
    cold = _probe(cache)                       # compiles every kernel it calls, writes the cache
    assert any(cache.rglob("*.nbi")), "the probe did not write numba's cache"
    warm = _probe(cache)                       # loads them
    assert cold.split()[0] == "raster" and len(cold.split()) >= 9
    assert warm == cold
