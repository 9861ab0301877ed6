#!/bin/bash
# The GPU check of README "On a GPU": run from the repo root on a CUDA machine where
# `pip install gsplat==1.5.3` has been done (its CUDA code compiles on first use; set
# TORCH_CUDA_ARCH_LIST, e.g. 9.0 on an H100, to build for that GPU only).
#   bash scripts/gpu_check.sh [OUTDIR]
# Writes logs and run.json files to OUTDIR (default gpu_check/) and prints a summary.
set -u
PY=${PYTHON:-python3}
OUTDIR=${1:-gpu_check}
mkdir -p "$OUTDIR"
export PYTHONUNBUFFERED=1
$PY -c "import torch, gsplat; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'gsplat', gsplat.__version__, torch.cuda.get_device_name())"
echo "== gsplat against the CPU rasterizer, CUDA tensors in the fused sampler"
$PY -m pytest -q -p no:cacheprovider tests/test_raster.py tests/test_hexplane_fused.py -k "gsplat or cuda" 2>&1 | tail -3
for mode in full rgb-only; do
  flag=""; [ "$mode" = rgb-only ] && flag="--rgb-only"
  echo "== demo on CUDA, 1000 fast steps, $mode"
  $PY -m engine train demo_capture --out "$OUTDIR/demo_$mode" --preset fast --restart --quiet $flag \
      > "$OUTDIR/train_$mode.log" 2>&1 || { echo "train failed:"; tail -20 "$OUTDIR/train_$mode.log"; continue; }
  $PY -m engine eval "$OUTDIR/demo_$mode" > "$OUTDIR/eval_$mode.json" 2> "$OUTDIR/eval_$mode.err" || tail -20 "$OUTDIR/eval_$mode.err"
  $PY -c "import json,sys; d=json.load(open(sys.argv[1])); print('  train_s', d['train_seconds'], 'psnr', d['psnr'], 'between', d['psnr_interframe'], 'ssim', d['ssim'], 'lpips', d['lpips'])" "$OUTDIR/eval_$mode.json"
done
echo "== tests that failed on the first GPU box (2026-11-23; tracebacks lost then), one process"
$PY -m pytest -q -p no:cacheprovider -p no:xdist --tb=short \
    tests/test_deformation.py tests/test_fine_deformation.py tests/test_bench.py tests/test_export_cli.py \
    tests/test_holes.py tests/test_geometry_losses.py tests/test_ablate_baselines.py \
    "tests/test_cli.py::test_demo_command" > "$OUTDIR/pytest_gpu.log" 2>&1
grep -E "^(FAILED|ERROR)|passed|failed" "$OUTDIR/pytest_gpu.log" | tail -30
