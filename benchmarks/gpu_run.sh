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
# Peers in the same run (issue 9): Warp ray cast vs Open3D ray_cast, Warp visibility vs Embree.
python3 benchmarks/peers.py "$rec" --device cuda --json "$out/peers_cuda.json"
# Speed against error (issue 9): SWEEP_SCENES = recordings with lighting_gt.json made with `photoreg synth`
# on the CPU machine (Mitsuba), e.g. ~/.cache/photoreg/bench_scenes/{tabletop,corner}-640x480-10f-64spp.
# The CPU rows of benchmarks/speed_error.csv are kept: copy the merged table and plot back from OUTDIR.
if [ -n "${SWEEP_SCENES:-}" ]; then
  cp benchmarks/speed_error.csv "$out/speed_error.csv"
  python3 -m photoreg bench sweep --recordings $SWEEP_SCENES --device cuda --frames 10 \
    --csv "$out/speed_error.csv" --plot "$out/speed_error.png"
fi
