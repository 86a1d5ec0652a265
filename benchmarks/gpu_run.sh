#!/usr/bin/env bash
# What ran on the GPU machine (after the wheels of warp-lang 1.19.0 and open3d 0.20.0 (CUDA build)
# were installed into /tmp/site): CUDA correctness, then the speed figures of benchmarks/gpu.md.
# usage: bash benchmarks/gpu_run.sh RECORDING OUTDIR
set -euo pipefail
rec=$1; out=$2
# open3d imports plotly/dash for its web visualiser; the GPU image lacks them: empty stand-ins.
mkdir -p /tmp/shim/plotly /tmp/shim/dash
touch /tmp/shim/plotly/__init__.py /tmp/shim/plotly/graph_objects.py
echo "html = dcc = Dash = None" > /tmp/shim/dash/__init__.py
export PYTHONPATH=/tmp/site:/tmp/shim:$PWD PYTHONUNBUFFERED=1 PHOTOREG_WARP_CACHE=/tmp/warpcache
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
python3 benchmarks/cuda_check.py "$rec" 4 | tee "$out/cuda_check.json"
for cfg in "1 169 4" "4 169 4" "4 64 3" "2 64 3"; do
  set -- $cfg
  python3 -m photoreg bench speed "$rec" --device cuda --frames 0:30 --warmup 3 --stride $1 --rays $2 --bands $3 \
    --json "$out/speed_s$1_r$2_b$3.json" 2>/dev/null
done
