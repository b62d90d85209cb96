#!/usr/bin/env bash
# The GPU evidence behind the README: the test suite on every Warp device (CPU and cuda:0: the
# device-parametrised tests and those marked `gpu`, such as CPU/CUDA agreement), then the renderer
# speed benchmark on both devices. Logs and JSON go to ${OUT:-gpu-out}.
#   usage: bash benchmarks/gpu_checks.sh [pytest selection...]
set -uo pipefail
out=${OUT:-gpu-out}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee "$out/gpu.txt"
python3 -c "import warp as wp; wp.init(); print('warp', wp.__version__, wp.get_devices())" | tee -a "$out/gpu.txt"
python3 -m pytest -q -rA -p no:cacheprovider -k "cuda or gpu or cpu_and_cuda" "${@:-tests}" 2>&1 | tee "$out/pytest_gpu.log" | tail -40
python3 -m benchmarks.bench_render --devices cuda:0 cpu --rays 10000 --cpu-rays 50 --json "$out/bench_render.json" \
  2>&1 | tee "$out/bench_render.log" | tail -8
