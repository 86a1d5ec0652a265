#!/usr/bin/env bash
# Throughput of `photoreg batch` against its worker count (benchmarks/gpu.md, "Many sessions on one GPU"):
# SESSIONS session files of $DATA/recordings/tum_fr1_rpy, frames FRAMES, "bare" (the recording alone) and/or "bunny" (with
# the object of sessions/tum_fr1_rpy.toml), `photoreg batch --workers W` for each W of WORKERS ("default": no
# --workers), with EXECUTOR (local or ray: `--executor`), for each package of CODES ("new": this tree; "old": the one
# in $OLD, an earlier commit's `git archive COMMIT photoreg | tar -x -C OLD`), timed whole; one JSON line per run
# appended to $OUT/batch_scale.jsonl, peak GPU memory (nvidia-smi, every 0.5 s) to $OUT/batch_mem.txt.
#   OUT=DIR DATA=PHOTOREG_DATA [DEVICE=cuda] [KINDS=bare|"bare bunny"] [SESSIONS=8] [FRAMES=0:40] [WORKERS="1 2 4 8"] \
#     [EXECUTOR=local|ray] [CODES="new old" OLD=DIR] bash benchmarks/batch_scale.sh
# On the GPU machine: `bash benchmarks/gpu_run.sh RECORDING OUTDIR batch` (its environment and stand-ins).
set -uo pipefail
DATA=${DATA:-/tmp/data}; DEVICE=${DEVICE:-cuda}; OUT=${OUT:?set OUT}; mkdir -p "$OUT"
KINDS=${KINDS:-bare}; SESSIONS=${SESSIONS:-8}; FRAMES=${FRAMES:-0:40}; WORKERS=${WORKERS:-"1 2 4 8"}
EXECUTOR=${EXECUTOR:-local}; CODES=${CODES:-new}
for kind in $KINDS; do
  rm -rf /tmp/bs_$kind; mkdir -p /tmp/bs_$kind
  for i in $(seq 1 $SESSIONS); do
    { echo "frames = \"$FRAMES\""; echo "device = \"$DEVICE\""
      echo '[recording]'; echo "path = \"$DATA/recordings/tum_fr1_rpy\""; echo 'format = "tum"'
      if [ $kind = bunny ]; then sed -n '/^\[\[objects\]\]/,/^albedo/p' sessions/tum_fr1_rpy.toml | sed "s#\${PHOTOREG_DATA}#$DATA#"; fi
      echo '[output]'; echo "dir = \"/tmp/bout_$kind/s$i\""; } > /tmp/bs_$kind/s$i.toml
  done
  for w in $WORKERS; do for code in $CODES; do
    tag=${kind}_${w}_${EXECUTOR}_$code
    rm -rf /tmp/bout_$kind /tmp/bo_$tag
    (while true; do nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits 2>/dev/null; sleep 0.5; done) > /tmp/mem_$tag.txt &
    sampler=$!
    t0=$(date +%s.%N)
    (cd "$([ $code = old ] && echo "${OLD:?set OLD}" || echo "$PWD")" && PYTHONPATH=$PWD:$PYTHONPATH python3 -m photoreg \
      batch /tmp/bs_$kind/*.toml $([ $w = default ] || echo --workers $w) --executor $EXECUTOR --out /tmp/bo_$tag) \
      > /tmp/batch_$tag.log 2>&1; rc=$?
    t1=$(date +%s.%N)
    kill $sampler 2>/dev/null; wait $sampler 2>/dev/null
    echo "$tag peak GPU memory MiB: $(sort -n /tmp/mem_$tag.txt | tail -1)" | tee -a $OUT/batch_mem.txt
    python3 - "$kind" "$w" "$t0" "$t1" "$rc" /tmp/bo_$tag/batch_summary.json "$EXECUTOR" "$code" <<'PY' | tee -a $OUT/batch_scale.jsonl
import json, sys
kind, w, t0, t1, rc, p = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4]), int(sys.argv[5]), sys.argv[6]
executor, code = sys.argv[7], sys.argv[8]
try:
    d = json.load(open(p))
except Exception as e:
    print(json.dumps({"kind": kind, "workers": w, "executor": executor, "code": code, "rc": rc, "error": str(e)})); sys.exit()
ss = d.get("sessions", d if isinstance(d, list) else [])
frames = sum(int(s.get("frames") or 0) for s in ss)
fps = [s.get("frames_per_s") for s in ss]
walls = [s.get("wall_s") for s in ss]
import os
print(json.dumps({"kind": kind, "workers": w, "executor": executor, "code": code, "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"), "rc": rc, "wall_s": round(t1 - t0, 2), "frames": frames,
                  "aggregate_fps": round(frames / (t1 - t0), 2), "session_fps": fps, "session_wall_s": walls, "status": [s.get("status") for s in ss]}))
PY
    grep -m1 "^batch:" /tmp/batch_$tag.log; tail -2 /tmp/batch_$tag.log
  done; done
done
