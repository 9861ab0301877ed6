#!/bin/bash
# The GPU check of README "On a GPU": run from the repo root on a CUDA machine where
# `pip install gsplat==1.5.3` has been done (its CUDA code compiles on first use, ~75 s; set
# TORCH_CUDA_ARCH_LIST, e.g. 9.0 on an H100, to build for that GPU only).
#   bash scripts/gpu_check.sh [OUTDIR]
# Writes logs and run.json files to OUTDIR (default gpu_check/) and prints a summary.
set -u
PY=${PYTHON:-python3}
OUTDIR=${1:-gpu_check}
mkdir -p "$OUTDIR"
export PYTHONUNBUFFERED=1
$PY -c "import torch, gsplat; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'gsplat', gsplat.__version__, torch.cuda.get_device_name())"
echo "== gsplat against the CPU rasterizer: parity (images, gradients) and speed"
$PY -m tools gpu-check > "$OUTDIR/gpu_check.txt" 2>&1; echo "  exit $?"; grep -E "parity|^\|" "$OUTDIR/gpu_check.txt"
for mode in full rgb-only; do
  flag=""; [ "$mode" = rgb-only ] && flag="--rgb-only"
  echo "== demo on CUDA, 1000 fast steps, $mode"
  $PY -m engine train demo_capture --out "$OUTDIR/demo_$mode" --preset fast --restart --quiet $flag \
      > "$OUTDIR/train_$mode.log" 2>&1 || { echo "train failed:"; tail -20 "$OUTDIR/train_$mode.log"; continue; }
  $PY -m engine eval "$OUTDIR/demo_$mode" > "$OUTDIR/eval_$mode.json" 2> "$OUTDIR/eval_$mode.err" || tail -20 "$OUTDIR/eval_$mode.err"
  $PY -c "import json,sys; d=json.load(open(sys.argv[1])); print('  train_s', d['train_seconds'], 'psnr', d['psnr'], 'between', d['psnr_interframe'], 'ssim', d['ssim'], 'lpips', d['lpips'])" "$OUTDIR/eval_$mode.json"
done
echo "== where a CUDA training step goes (300 demo steps, RGB then guided)"
$PY -m tools bench-step demo_capture --steps 300 --device cuda > "$OUTDIR/bench_step_cuda.txt" 2>&1
grep -E "step ms|raster|admit|x \(target" "$OUTDIR/bench_step_cuda.txt" | head -12
echo "== the test suite on this box (bpy tests need Python 3.11: they fail or skip elsewhere)"
$PY -c "import engine.train.loop.budget as b; b.warm_up_runtime('cpu')"  # numba caches once, not per worker
$PY -m pytest -q -p no:cacheprovider --tb=short tests $($PY -c "import xdist" 2>/dev/null && echo "-n 8") \
    > "$OUTDIR/pytest_gpu.log" 2>&1
grep -E "^(FAILED|ERROR)|passed|failed" "$OUTDIR/pytest_gpu.log" | tail -30
