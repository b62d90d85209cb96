#!/usr/bin/env bash
# The GPU evidence behind the README, in parts that each fit one device call:
#   bash benchmarks/gpu_checks.sh tests      the test suite's CUDA cases (every device-parametrised test
#                                            on cuda:0, CPU/CUDA agreement), the renderer speed benchmark and
#                                            the correlation's NumPy path against its Warp path on cuda:0, and
#                                            an Nsight Compute profile of the renderer before/after its speed settings
#   bash benchmarks/gpu_checks.sh campaign   `synthbos paper --full` on cuda:0 and an f-number sweep
#   bash benchmarks/gpu_checks.sh scaling    campaign throughput on 1, 2, 4 GPUs through Dask (bench_scaling)
#   bash benchmarks/gpu_checks.sh stages     per-stage times of a pair on cuda:0 and the CPU (bench_stages), and
#                                            `synthbos paper --full` processing on the GPU (ALSO_CPU=1: and on the CPU)
# The device image lacks some pure-Python dependencies (dask, pynrrd, imageio, hypothesis, threadpoolctl): carry them as
# wheels in .whl/ and install them into /tmp/site first (see the README's GPU section).
# Logs, tables and figures are packed into ${OUT:-gpu-out}/gpu-<part>.tar.gz.
set -uo pipefail
part=${1:-tests}
out=${OUT:-gpu-out}
work=$(mktemp -d)
mkdir -p "$out"
export PYTHONUNBUFFERED=1
command -v synthbos >/dev/null || synthbos() { python3 -m synthbos.benchmarks.cli "$@"; }
{ date -u; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv;
  python3 -c "import warp as wp; wp.init(); print('warp', wp.__version__, wp.get_devices())"; } > "$work/gpu.txt" 2>&1
cat "$work/gpu.txt"
if [ "$part" = stages ] || [ "$part" = campaign ]; then
  # Timed runs: the bytecode compiled once, as pip install leaves it (the device image sets
  # PYTHONDONTWRITEBYTECODE, so every process would compile every module it imports), and the kernels
  # compiled by a warm-up campaign.
  python3 -m compileall -q -j 0 . ${PYTHONPATH//:/ } > /dev/null 2>&1
  synthbos paper --quick --device cuda:0 --workers 14 -q --out "$work/warm-up" > /dev/null 2>&1
  rm -rf "$work/warm-up"
fi
if [ "$part" = tests ]; then
  python3 -m pytest -q -rA -p no:cacheprovider -m gpu tests \
    > "$work/pytest_gpu.log" 2>&1
  grep -E "passed|failed|CPU vs CUDA|^FAILED" "$work/pytest_gpu.log" | tail -12
  # the renderer before its speed settings first (the reference of the differences), then today's default
  plain=field=float32,dot_order=pattern,rays_per_group=1
  python3 -m synthbos.benchmarks.bench_render --devices cuda:0 cpu --rays 10000 --cpu-rays 50 --repeats 3 \
    --variants $plain default field=float16 field=texture16 --cpu-variants $plain default \
    --json "$work/bench_render.json" > "$work/bench_render.log" 2>&1
  tail -8 "$work/bench_render.log"
  if command -v ncu >/dev/null; then  # what limits the gradient image's kernel, before and after
    timeout 240 ncu --clock-control none -k regex:render_rays --section SpeedOfLight --section MemoryWorkloadAnalysis \
      --section Occupancy --section LaunchStats --section WarpStateStats \
      python3 -m synthbos.benchmarks.bench_render --devices cuda:0 --rays 2000 --profile --variants $plain default \
      > "$work/ncu_render.log" 2>&1
    grep -E "render_rays|Duration|L1/TEX Cache Throughput|L2 Cache Throughput|DRAM Throughput|Compute \(SM\) Throughput|Registers Per|Achieved Occupancy|Theoretical Occupancy" \
      "$work/ncu_render.log" | head -48
  fi
  python3 -m synthbos.benchmarks.bench_correlation --devices cuda:0 --sizes 512 1024 --repeat 10 --profile \
    > "$work/bench_correlation.log" 2>&1
  grep -A12 "^pair" "$work/bench_correlation.log"
elif [ "$part" = stages ]; then
  python3 -m synthbos.benchmarks.bench_stages --devices cpu cuda:0 --rays 10000 --cpu-rays 100 --batch 400 --cpu-batch 4 --paper-full \
    ${ALSO_CPU:+--also-cpu-processing} --workers 14 --json "$work/bench_stages.json" > "$work/bench_stages.log" 2>&1
  cat "$work/bench_stages.log"
  cp "$work/bench_stages.json" "$work/bench_stages.log" "$out/" 2>/dev/null
elif [ "$part" = scaling ]; then
  gpus=$(nvidia-smi --query-gpu=index --format=csv,noheader | paste -sd, -)
  counts=$(python3 -c "n=len('$gpus'.split(',')); print(','.join(str(c) for c in (1, 2, 4, 8) if c <= n))")
  python3 -m synthbos.benchmarks.bench_scaling --device cuda:0 --gpus "$gpus" --counts "$counts" \
    --pairs-per-gpu "${PAIRS_PER_GPU:-8}" --noise "${NOISE:-0,3}" --out "$work/scaling" > "$work/scaling.log" 2>&1
  tail -12 "$work/scaling.log"
  cp "$work/scaling/"* "$out/" 2>/dev/null
else
  synthbos paper --full --device cuda:0 --out "$work/paper-full" --workers 14 -q > "$work/paper_full.log" 2>&1
  tail -16 "$work/paper_full.log"
  printf '[rays]\nper_dot = 1000\n' > "$work/sweep.toml"
  synthbos sweep "$work/sweep.toml" --param f_number=4,8,11,22,32 --size quick --device cuda:0 --workers 14 -q \
    --out "$work/sweep-fnumber" > "$work/sweep.log" 2>&1
  tail -3 "$work/sweep.log"
  mkdir -p "$work/keep"
  cp "$work"/paper-full/{results.csv,results.json,fig4.png,fig5.png,fig_density.png,campaign.json} "$work/keep/" 2>/dev/null
  cp "$work"/sweep-fnumber/{sweep.csv,sweep.json,sweep.png} "$work/keep/" 2>/dev/null
fi
tar -czf "$out/gpu-$part.tar.gz" -C "$work" --exclude=paper-full --exclude=sweep-fnumber .
