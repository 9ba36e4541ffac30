#!/usr/bin/env bash
# GPU checks in one call, for a machine with a CUDA device and the package importable by $PY:
#   the CUDA variants of the test suite, the kernel benchmark and whole-fit benchmarks on cuda:0.
# Usage: scripts/gpu_check.sh OUT_DIR [FIT_CASES...]   (default cases: quadruped fox120)
# Each stage has its own time limit (seconds; environment TESTS_S, KERNELS_S, FIT_S) so one slow stage
# cannot starve the next; logs and the benchmark JSON are copied to OUT_DIR as the stages end.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${1:?usage: scripts/gpu_check.sh OUT_DIR [FIT_CASES...]}
shift
CASES=${*:-quadruped fox120}
PY=${PY:-python3}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
stamp() { echo "[$(date +%T)] $*"; }

stamp "device"
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm --format=csv 2>&1 | tee "$OUT/device.txt"
$PY -c "import torch, warp as wp; wp.init(); print('torch', torch.__version__, torch.cuda.get_device_name(0)); print('warp', wp.__version__, wp.get_cuda_devices())" 2>&1 | tee -a "$OUT/device.txt"

stamp "CUDA tests"
timeout "${TESTS_S:-200}" $PY -m pytest -q -k cuda -p no:cacheprovider --continue-on-collection-errors -rfEs tests 2>&1 | tee "$OUT/tests-cuda.log" | tail -25
stamp "tests rc=${PIPESTATUS[0]}"

stamp "kernel benchmark"
timeout "${KERNELS_S:-90}" $PY scripts/bench_kernels.py --device cuda 2>&1 | tee "$OUT/kernels-cuda.log" | tail -30
cp benchmarks/kernels-cuda.json "$OUT/" 2>/dev/null

for case in $CASES; do
  stamp "fit $case"
  echo "== $case" >>"$OUT/fits.err"  # one log for all cases: few files under OUT (some hosts fetch only a handful)
  timeout "${FIT_S:-240}" $PY scripts/bench_fit.py --device cuda --cases "$case" --out-dir runs/gpu 2>>"$OUT/fits.err" | tail -3
  tail -5 "$OUT/fits.err"
  cp benchmarks/fit-cuda.json "$OUT/" 2>/dev/null
done
stamp "done"
