#!/usr/bin/env bash
# What ran on the GPU machine (after the wheels of warp-lang 1.19.0, open3d 0.20.0 (CUDA build) and
# pyrender 0.1.45 with its pure-Python dependencies (trimesh among them: gpu_profile.py needs it) were
# installed into /tmp/site, and libEGL and its kin unpacked from their Debian packages with `dpkg -x` into a
# folder on LD_LIBRARY_PATH: open3d's CUDA build loads libEGL.so.1, which the image lacks): CUDA correctness,
# then the figures of benchmarks/gpu.md, benchmarks/speed.md and benchmarks/renderers.md. benchmarks/gpu_carry.sh
# prepares all of that (and the data, and an earlier package for the A/B steps) and says which calls carry it over.
# (2026-11-26: ../shared/hooks/device-wheels' chunks of 60 MB leave no room for the 10 MB working tree in a
# 64 MiB call: split at 48 MB; its install.sh stopped after the first wheel (`tail | head` under pipefail), so the
# wheels were cut from the joined chunks by their sizes in Python.)
# usage: bash benchmarks/gpu_run.sh RECORDING OUTDIR STEP...
#   speed      cuda_check, `photoreg bench speed` at four settings and on the demo (with and without the
#              traced light), gpu_profile.py, peers.py
#   render     `photoreg bench speed` with an object inserted (sessions/tum_fr1_rpy.toml, data/demo/session.toml):
#              the render stage (R_TRV, G-buffer by pyrender on EGL, composite) timed with the rest
#   renderers  `photoreg bench renderers --device cuda $RENDER_ARGS` on RENDER_SCENES (a scene cache made here
#              with `photoreg bench renderers`, e.g. ~/.cache/photoreg/bench_scenes; RENDER_ARGS: its --size,
#              --frames and --spp)
#   history    TUM stride 4 / 64 rays / 3 bands and the demo with its traced light, with and without the
#              history of samples (--no-history)
#   blas       the solve's BLAS threads (OPENBLAS_NUM_THREADS 1, 4, 16) at stride 4 / 64 rays / 3 bands
#              and on the demo with its traced light
#   every      the lighting estimated on every n-th frame (lighting.every, --every): TUM alone and with the bunny
#              at stride 4 / 64 rays / 3 bands, alone at stride 1 / 169 rays / 4 bands, the demo with its traced
#              light; the settings alternate (calls differ by 20-40%); every run's figures into OUTDIR/every.json
#   refine     the demo alone and with its object, its held light refined every 5th frame (lighting.sun_refine_every
#              5, the default) against every frame (1), alternating, two rounds (OUTDIR/refine.json)
#   live       (needs the websockets wheel too) `photoreg serve --device cuda --meshes $PHOTOREG_DATA/meshes` and `photoreg stream RECORDING --session
#              sessions/tum_fr1_rpy.toml` through it (the bunny composited by the server, JPEG back), every 1 and 4
#              and --async: frames/s and latency as a client sees them (OUTDIR/live_*.json, the stream's summary.json)
#   bounce     the observed bounce (lighting.bounce_observed) on CUDA: cuda_check on RECORDING (4 frames) and on the
#              demo (8 frames), then `photoreg bench speed` with it and without (--no-observed-bounce), alternating,
#              two rounds: RECORDING at stride 4 / 64 rays / 3 bands and stride 1 / 169 / 4, the bunny
#              (sessions/tum_fr1_rpy.toml) and the demo's session (OUTDIR/bounce.json)
#   async      the lighting estimated in a worker thread beside the frames (lighting.asynchronous, --async):
#              async_check.py on RECORDING and on the demo (8 frames), then `photoreg bench speed` in line and
#              asynchronous, alternating, ASYNC_ROUNDS (default "1 2") rounds: RECORDING at stride 4 / 64 rays / 3 bands
#              and stride 1 / 169 / 4, the bunny (sessions/tum_fr1_rpy.toml), the demo's session (OUTDIR/async.json)
#   process    the asynchronous worker's robust solves in a child process (lighting.solve_process, the default) against
#              the worker thread (--no-solve-process): async_check.py on RECORDING and on the demo (8 frames), then
#              `photoreg bench speed --async` both ways, alternating, PROCESS_ROUNDS (default "1 2") rounds
#              (OUTDIR/process.json)
#   held       frames that only hold the lighting (`--every 1000`: no estimate after the first frame, no worker) against
#              `--async`, alternating, HELD_ROUNDS (default "1 2") rounds: what the worker still costs the frames
#              (OUTDIR/held.json)
#   ab         this tree against the package in $OLD (an earlier commit: `git archive COMMIT photoreg | tar -x -C OLD`),
#              `photoreg bench speed $AB_FLAGS` alternating (the old first in odd rounds, this tree in even), AB_ROUNDS (default "1 2") rounds: RECORDING at stride 4 /
#              64 rays / 3 bands and stride 1 / 169 / 4, the bunny (sessions/tum_fr1_rpy.toml) (OUTDIR/ab.json); AB_RUNS
#              (comma-separated "KIND STRIDE RAYS BANDS", KIND bare, bunny or demo) picks other settings
#   gbuffer    the objects' G-buffer ray-traced (render.gbuffer = raycast, --gbuffer) against pyrender's draw on EGL:
#              composite_ab.py of the two on CUDA (TUM with the bunny, the demo's session, 8 frames each; into
#              OUTDIR/gbuffer_composite_ab.jsonl), then `photoreg bench speed` of TUM with the bunny both ways,
#              alternating, GBUFFER_ROUNDS (default "1 2") rounds, at stride 1 / 169 / 4 and 4 / 64 / 3, `--every 1000`
#              (held) and `--async` (OUTDIR/gbuffer.json)
#   gbcheck    the G-buffer tests of tests/test_render.py on this machine (pyrender on NVIDIA's EGL; the raycast and
#              varying-attribute kernels (textures, vertex colours, smooth normals) on the CPU and on CUDA; pytest's
#              wheels carried in .carry/pytest), then benchmarks/gbuffer_check.py on TUM with the bunny and the demo's
#              session, 8 frames each on CUDA (OUTDIR/gbuffer_check.jsonl, the frames differing most in
#              OUTDIR/gbuffer_check_*.npz)
#   blur       the motion blur's unit tests (tests/test_motion_blur.py, the ones without Mitsuba), then `photoreg bench
#              speed` of TUM with the bunny (raycast G-buffer, stride 4 / 64 / 3, held and --async) with --shutter 0
#              and 0.016, alternating, BLUR_ROUNDS (default "1 2") rounds (OUTDIR/blur.json)
#   tracking   camera tracking (--no-poses) on CUDA: tests/test_tracking.py's tests that the carried frames allow,
#              then benchmarks/tracking.py on RECORDING's carried frames, every 1st, 4th and 8th
#              (OUTDIR/tracking_cuda.md)
#   fusion     tests/test_fusion_kernels.py on CUDA where it asks for it (the volume's size limit and its restart):
#              OUTDIR/fusion_pytest.txt
#   meshgt     MESH_RECS (recordings made with `photoreg synth ... --insert-mesh FILE`, carried over): `photoreg run
#              --device cuda` of each one's session with the G-buffer drawn (pyrender) and ray-traced, smooth as written
#              and flat (objects.smooth = false), each scored with `photoreg score --composite` (OUTDIR/meshgt_*.json)
#   sweep      `photoreg bench sweep --device cuda` on SWEEP_SCENES (recordings with lighting_gt.json
#              made here with `photoreg synth`); VOXELS (default 0.01,0.02) restricts it to fit one call
#   batch      benchmarks/batch_scale.sh: `photoreg batch` over the worker counts WORKERS (its other variables too;
#              DATA defaults to $PHOTOREG_DATA), into OUTDIR/batch_scale.jsonl and OUTDIR/batch_mem.txt
#   run        benchmarks/run_ab.py: `photoreg run` (its files written) of this tree against the package in $OLD,
#              alternating, RUN_ROUNDS (default 2) rounds, after a warm-up run of each session: the bunny
#              (sessions/tum_fr1_rpy.toml, RUN_FRAMES, default 0:100) and the demo's session (40 frames), in line and
#              --async (OUTDIR/run_ab.json)
#   liveab     benchmarks/live_ab.py: `photoreg serve --device cuda` and `photoreg stream RECORDING` of this tree against
#              the package in OLD, alternating, LIVE_ROUNDS (default 2) rounds of frames LIVE_FRAMES (default 0:100): TUM
#              with the bunny (sessions/tum_fr1_rpy.toml) --async and in line, TUM alone --async (OUTDIR/live_ab.json);
#              then benchmarks/live_split.py through this tree's server, a process per connection and --threads
#   readab     frames read on several threads: `photoreg run` of TUM alone and with the bunny (--async, run_ab.py) and
#              `photoreg stream` of TUM alone (--async; PNG and raw rgb8/u16 frames, live_ab.py), this tree against
#              the package in OLD, alternating (OUTDIR/read_run_ab.json, OUTDIR/read_live_ab.json)
#   rstride    the objects' shadows sampled at their own stride (render.stride, --render-stride) 1 against 4 (the
#              default), TUM with the bunny (sessions/tum_fr1_rpy.toml) at lighting stride 1 / 169 / 4, `--every 1000`
#              (held) and `--async`, alternating, RSTRIDE_ROUNDS (default "1 2") rounds (OUTDIR/rstride.json)
#   decodeab   a connection's frames decoded two at a time by the server: `photoreg stream` of TUM alone (--async; PNG
#              frames, raw rgb8/u16, PNG with --window 3) and with the bunny (sessions/tum_fr1_rpy.toml, --async), this
#              tree against the package in OLD, alternating, LIVE_ROUNDS (default 2) rounds (OUTDIR/decode_live_ab.json)
#   patchab    the composite handed to the server as its changed box (host.CompositePatch): `photoreg stream` with the
#              bunny (sessions/tum_fr1_rpy.toml) --async with PNG and with raw frames, and in line (composites compared),
#              this tree against the package in OLD, alternating, LIVE_ROUNDS (default 2) rounds (OUTDIR/patch_live_ab.json)
#   serve      benchmarks/serve_clients.py: SERVE_CLIENTS (default 4) `photoreg stream RECORDING` clients at once through
#              `photoreg serve --device cuda` with and without --threads, SERVE_ROUNDS (default 1) rounds of
#              frames SERVE_FRAMES (default 0:40), into OUTDIR/serve_clients.json
set -euo pipefail
rec=$1; out=$2; shift 2
# open3d imports plotly/dash for its web visualiser; the GPU image lacks them: empty stand-ins.
mkdir -p /tmp/shim/plotly /tmp/shim/dash
touch /tmp/shim/plotly/__init__.py /tmp/shim/plotly/graph_objects.py
echo "html = dcc = Dash = None" > /tmp/shim/dash/__init__.py
# pyrender imports pyglet for its (unused) viewer; pyglet 1.5 then needs libGLU, which the image lacks.
mkdir -p /tmp/shim/pyglet
printf 'options = {}\nclock = None\nclass window:\n    class Window:\n        pass\n' > /tmp/shim/pyglet/__init__.py
export PYTHONPATH=/tmp/shim:/tmp/site:$PWD PYTHONUNBUFFERED=1 PHOTOREG_WARP_CACHE=/tmp/warpcache
export PYOPENGL_PLATFORM=egl
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
# input_of KIND: what `photoreg bench speed` reads for bare (RECORDING), bunny (its session) and demo (the demo's session)
input_of() {
  case $1 in bare) echo "$rec" ;; bunny) echo sessions/tum_fr1_rpy.toml ;; demo) echo data/demo/session.toml ;; esac
}
# alternate DIR ROUNDS MODE1 FLAGS1 MODE2 FLAGS2: per round, `photoreg bench speed` at four settings (RECORDING at
# stride 4 / 64 rays / 3 bands and stride 1 / 169 / 4, the bunny's session, the demo's), each in both modes, the
# figures into DIR/<setting>_s<stride>_<mode>_<round>.json; merge DIR OUT: those files into one JSON object.
alternate() {
  local dir=$1 rounds=$2 modes=("$3" "$5") flags=("$4" "$6") round run kind stride rays bands src i
  mkdir -p "$dir"
  for round in $rounds; do
    for run in "bare 4 64 3" "bare 1 169 4" "bunny 4 64 3" "demo 4 64 5"; do
      read -r kind stride rays bands <<< "$run"
      src=$(input_of $kind)
      for i in 0 1; do
        python3 -m photoreg bench speed "$src" --device cuda --frames 0:30 --warmup 3 --stride $stride --rays $rays \
          --bands $bands ${flags[$i]} --json "$dir/${kind}_s${stride}_${modes[$i]}_$round.json" 2>/dev/null
      done
    done
  done
}
merge() {
  python3 -c "import json, pathlib, sys; json.dump({f.stem: json.loads(f.read_text()) for f in sorted(pathlib.Path(sys.argv[1]).glob('*.json'))}, open(sys.argv[2], 'w'), indent=1)" "$1" "$2"
}
for step in "$@"; do
  case $step in
    speed)
      python3 benchmarks/cuda_check.py "$rec" 4 | tee "$out/cuda_check.json"
      for cfg in "1 169 4" "4 169 4" "4 64 3" "2 64 3"; do
        set -- $cfg
        python3 -m photoreg bench speed "$rec" --device cuda --frames 0:30 --warmup 3 --stride $1 --rays $2 \
          --bands $3 --json "$out/speed_s$1_r$2_b$3.json" 2>/dev/null
      done
      # The demo holds a traced light: the joint solve's cost, with and without the sun and bounce terms.
      python3 -m photoreg bench speed data/demo --device cuda --frames 0:30 --warmup 3 --stride 4 --rays 64 \
        --bands 5 --json "$out/speed_demo_sun.json" 2>/dev/null
      python3 -m photoreg bench speed data/demo --device cuda --frames 0:30 --warmup 3 --stride 4 --rays 64 \
        --bands 5 --no-sun --no-bounce --json "$out/speed_demo_nosun.json" 2>/dev/null
      python3 benchmarks/gpu_profile.py "$rec" --device cuda --json "$out/profile_cuda.json"
      # Peers in the same run: Warp ray cast vs Open3D ray_cast, Warp visibility vs Embree.
      python3 benchmarks/peers.py "$rec" --device cuda --json "$out/peers_cuda.json" ;;
    history)
      # The history of samples (lighting.history): TUM and the demo with and without it, in one call.
      for h in "" "--no-history"; do
        tag=$([ -z "$h" ] && echo on || echo off)
        python3 -m photoreg bench speed "$rec" --device cuda --frames 0:30 --warmup 3 --stride 4 --rays 64 \
          --bands 3 $h --json "$out/history_${tag}_s4_r64_b3.json" 2>/dev/null
        python3 -m photoreg bench speed data/demo --device cuda --frames 0:30 --warmup 3 --stride 4 --rays 64 \
          --bands 5 $h --json "$out/history_${tag}_demo_sun.json" 2>/dev/null
      done ;;
    blas)
      for n in 1 4 16; do
        OPENBLAS_NUM_THREADS=$n python3 -m photoreg bench speed "$rec" --device cuda --frames 0:30 --warmup 3 \
          --stride 4 --rays 64 --bands 3 --json "$out/blas${n}_s4_r64_b3.json" 2>/dev/null
        OPENBLAS_NUM_THREADS=$n python3 -m photoreg bench speed data/demo --device cuda --frames 0:30 --warmup 3 \
          --stride 4 --rays 64 --bands 5 --json "$out/blas${n}_demo_sun.json" 2>/dev/null
      done ;;
    render)
      # The full per-frame pipeline with an object inserted (R_TRV, G-buffer, composite timed too, the `render`
      # stage): the bunny of sessions/tum_fr1_rpy.toml (PHOTOREG_DATA must hold recordings/tum_fr1_rpy and
      # meshes/bunny_5k.obj) beside the recording without objects, and the demo's session.
      for cfg in "4 64 3" "1 169 4"; do
        set -- $cfg
        python3 -m photoreg bench speed "$rec" --device cuda --frames 0:30 --warmup 3 --stride $1 --rays $2 \
          --bands $3 --json "$out/render_bare_s$1_r$2_b$3.json" 2>/dev/null
        python3 -m photoreg bench speed sessions/tum_fr1_rpy.toml --device cuda --frames 0:30 --warmup 3 \
          --stride $1 --rays $2 --bands $3 --json "$out/render_bunny_s$1_r$2_b$3.json" 2>/dev/null
      done
      python3 -m photoreg bench speed data/demo/session.toml --device cuda --frames 0:30 --warmup 3 --stride 4 \
        --rays 64 --bands 5 --json "$out/render_demo.json" 2>/dev/null ;;
    renderers)
      mkdir -p "$out/renderers"
      python3 -m photoreg bench renderers --device cuda --synth-dir "$RENDER_SCENES" ${RENDER_ARGS:-} \
        --results-dir "$out/renderers" --md "$out/renderers/renderers.md" --plot "$out/renderers/renderers.png" || true
      ls "$out/renderers"/renderers_cuda_*.json ;;   # the rows; the report is redrawn where matplotlib is
    every)
      mkdir -p /tmp/every
      for run in "bare 4 64 3 1" "bare 4 64 3 4" "bare 4 64 3 2" "bare 4 64 3 8" "bare 4 64 3 1" "bare 4 64 3 4" \
                 "bunny 4 64 3 1" "bunny 4 64 3 4" "bunny 4 64 3 1" "bunny 4 64 3 4" "bare 1 169 4 1" \
                 "bare 1 169 4 4" "demo 4 64 5 1" "demo 4 64 5 4"; do
        set -- $run
        src=$(input_of $1)
        python3 -m photoreg bench speed "$src" --device cuda --frames 0:30 --warmup 3 --stride $2 --rays $3 \
          --bands $4 --every $5 --json "/tmp/every/$(ls /tmp/every | wc -l)_$1_s$2_n$5.json" 2>/dev/null
      done
      python3 -c "import json, pathlib, sys; fs = sorted(pathlib.Path('/tmp/every').glob('*.json'), key=lambda p: int(p.name.split('_')[0])); json.dump([dict(json.loads(f.read_text()), run=f.stem) for f in fs], open(sys.argv[1], 'w'), indent=1)" "$out/every.json" ;;
    refine)
      # A held light refined every 5th frame (lighting.sun_refine_every 5, the default) against every frame (1),
      # alternating, two rounds: the demo (its traced light held from the first frames), alone and with its object.
      mkdir -p /tmp/refine
      for k in 5 1; do
        printf '[recording]\npath = "%s/data/demo"\n[lighting]\nsun_refine_every = %s\n' "$PWD" $k > /tmp/refine/bare$k.toml
        sed -e "s#^path = .*#path = \"$PWD/data/demo\"#" -e "s#^mesh = \"#mesh = \"$PWD/data/demo/#" \
          data/demo/session.toml > /tmp/refine/object$k.toml
        printf '[lighting]\nsun_refine_every = %s\n' $k >> /tmp/refine/object$k.toml
      done
      for round in 1 2; do
        for run in bare5 bare1 object5 object1; do
          python3 -m photoreg bench speed /tmp/refine/$run.toml --device cuda --frames 0:30 --warmup 3 --stride 4 \
            --rays 64 --bands 5 --json "/tmp/refine/${run}_$round.json" 2>/dev/null
        done
      done
      python3 -c "import json, pathlib, sys; json.dump({f.stem: json.loads(f.read_text()) for f in sorted(pathlib.Path('/tmp/refine').glob('*.json'))}, open(sys.argv[1], 'w'), indent=1)" "$out/refine.json" ;;
    live)
      python3 -m photoreg serve --device cuda --port 8765 --meshes "$PHOTOREG_DATA/meshes" > /tmp/serve.log 2>&1 &
      srv=$!
      for i in $(seq 90); do grep -q "listening on" /tmp/serve.log && break; sleep 1; done
      for mode in "n1 --every 1" "n4 --every 4" "async --async"; do
        read -r name flags <<< "$mode"
        python3 -m photoreg stream "$rec" --url ws://127.0.0.1:8765 --session sessions/tum_fr1_rpy.toml \
          --frames 0:30 $flags --out /tmp/live_$name --quiet
        cp /tmp/live_$name/summary.json "$out/live_$name.json"
      done
      kill $srv; wait $srv || true; tail -3 /tmp/serve.log ;;
    async)
      python3 benchmarks/async_check.py "$rec" 8 | tee "$out/async_check_tum.json"
      python3 benchmarks/async_check.py data/demo 8 | tee "$out/async_check_demo.json"
      alternate /tmp/async "${ASYNC_ROUNDS:-1 2}" inline "" async --async
      merge /tmp/async "$out/async.json" ;;
    process)
      python3 benchmarks/async_check.py "$rec" 8 | tee "$out/async_check_tum.json"
      python3 benchmarks/async_check.py data/demo 8 | tee "$out/async_check_demo.json"
      alternate /tmp/process "${PROCESS_ROUNDS:-1 2}" process --async thread "--async --no-solve-process"
      merge /tmp/process "$out/process.json" ;;
    held)
      alternate /tmp/held "${HELD_ROUNDS:-1 2}" held "--every 1000" async --async
      merge /tmp/held "$out/held.json" ;;
    bounce)
      # BOUNCE_ROUNDS (default "1 2"): rounds of this call; CHECK=0 leaves the cuda_check runs out (a later call
      # of the same warm machine: the runs of earlier calls stay in /tmp/bounce and end up in bounce.json too).
      if [ "${CHECK:-1}" = 1 ]; then
        python3 benchmarks/cuda_check.py "$rec" 4 | tee "$out/cuda_check_tum.json"
        python3 benchmarks/cuda_check.py data/demo 8 | tee "$out/cuda_check_demo.json"
      fi
      alternate /tmp/bounce "${BOUNCE_ROUNDS:-1 2}" on "" off --no-observed-bounce
      merge /tmp/bounce "$out/bounce.json" ;;
    ab)
      rm -rf /tmp/ab; mkdir -p /tmp/ab   # no figures of an earlier ab step merged in
      IFS=, read -r -a runs <<< "${AB_RUNS:-bare 4 64 3,bare 1 169 4,bunny 4 64 3}"
      for round in ${AB_ROUNDS:-1 2}; do
        for run in "${runs[@]}"; do
          read -r kind stride rays bands <<< "$run"
          src=$(realpath "$(input_of $kind)")
          codes="old new"; [ $((round % 2)) = 0 ] && codes="new old"   # each first in every other round
          for code in $codes; do   # the old package first on the path, run from elsewhere (not this tree's)
            (cd $([ $code = old ] && echo "$OLD" || echo "$PWD") && PYTHONPATH=$PWD:$PYTHONPATH python3 -m photoreg \
              bench speed "$src" --device cuda --frames 0:30 --warmup 3 --stride $stride --rays $rays --bands $bands \
              ${AB_FLAGS:-} --json "/tmp/ab/${kind}_s${stride}_${code}_$round.json" 2>/dev/null)
          done
        done
      done
      merge /tmp/ab "$out/ab.json" ;;
    rstride)
      mkdir -p /tmp/rstride
      for round in ${RSTRIDE_ROUNDS:-1 2}; do
        for mode in "held --every 1000" "async --async"; do
          read -r tag flags <<< "$mode"
          for rs in 1 4; do
            python3 -m photoreg bench speed sessions/tum_fr1_rpy.toml --device cuda --frames 0:30 --warmup 3 --stride 1 \
              --rays 169 --bands 4 --render-stride $rs $flags --json "/tmp/rstride/${tag}_r${rs}_$round.json" 2>/dev/null
          done
        done
      done
      merge /tmp/rstride "$out/rstride.json" ;;
    gbuffer)
      for session in sessions/tum_fr1_rpy.toml data/demo/session.toml; do
        python3 benchmarks/composite_ab.py . $session 0:8 cuda render.gbuffer=raycast 2>/dev/null \
          | tee -a "$out/gbuffer_composite_ab.jsonl"
      done
      rm -rf /tmp/gbuffer; mkdir -p /tmp/gbuffer
      for round in ${GBUFFER_ROUNDS:-1 2}; do
        backends="pyrender raycast"; [ $((round % 2)) = 0 ] && backends="raycast pyrender"   # each first in turn
        for mode in "held --every 1000" "async --async"; do
          read -r tag flags <<< "$mode"
          for run in "1 169 4" "4 64 3"; do
            read -r stride rays bands <<< "$run"
            for g in $backends; do
              python3 -m photoreg bench speed sessions/tum_fr1_rpy.toml --device cuda --frames 0:30 --warmup 3 \
                --stride $stride --rays $rays --bands $bands --gbuffer $g $flags \
                --json "/tmp/gbuffer/${tag}_s${stride}_${g}_$round.json" 2>/dev/null
            done
          done
        done
      done
      merge /tmp/gbuffer "$out/gbuffer.json" ;;
    gbcheck)
      [ -d .carry/pytest ] && python3 -m pip install -q --no-index --no-deps --target /tmp/site .carry/pytest/*.whl
      python3 -m pytest -q -p no:cacheprovider tests/test_render.py \
        -k "raycast or egl or window_holds or texture or colours or smooth or materials or kenney" 2>&1 \
        | tail -15 | tee "$out/gbuffer_pytest.txt" || true   # the checks below whatever the tests say
      for session in sessions/tum_fr1_rpy.toml data/demo/session.toml; do
        python3 benchmarks/gbuffer_check.py $session 0:8 cuda "$out/gbuffer_check_${session//\//_}.npz" \
          2>/dev/null | tee -a "$out/gbuffer_check.jsonl"
      done ;;
    blur)
      [ -d .carry/pytest ] && python3 -m pip install -q --no-index --no-deps --target /tmp/site .carry/pytest/*.whl
      python3 -m pytest -q -p no:cacheprovider tests/test_motion_blur.py -k "spreads or show_through or needs" 2>&1 \
        | tail -3 | tee "$out/blur_pytest.txt" || true
      rm -rf /tmp/blur; mkdir -p /tmp/blur
      for round in ${BLUR_ROUNDS:-1 2}; do
        shutters="0 0.016"; [ $((round % 2)) = 0 ] && shutters="0.016 0"   # each first in turn
        for mode in "held --every 1000" "async --async"; do
          read -r tag flags <<< "$mode"
          for sh in $shutters; do
            python3 -m photoreg bench speed sessions/tum_fr1_rpy.toml --device cuda --frames 0:30 --warmup 3 \
              --stride 4 --rays 64 --bands 3 --gbuffer raycast --shutter $sh $flags \
              --json "/tmp/blur/${tag}_shutter${sh}_$round.json" 2>/dev/null
          done
        done
      done
      merge /tmp/blur "$out/blur.json" ;;
    tracking)
      [ -d .carry/pytest ] && python3 -m pip install -q --no-index --no-deps --target /tmp/site .carry/pytest/*.whl
      python3 -m pytest -q -p no:cacheprovider tests/test_tracking.py -k "matched or predicted or ate_is" 2>&1 \
        | tail -3 | tee "$out/tracking_pytest.txt" || true
      python3 benchmarks/tracking.py --recordings "$(basename "$rec")" --steps 1,4,8 --device cuda 2>/dev/null \
        | grep "^|" | tee "$out/tracking_cuda.md" ;;
    fusion)
      [ -d .carry/pytest ] && python3 -m pip install -q --no-index --no-deps --target /tmp/site .carry/pytest/*.whl
      python3 -m pytest -q -p no:cacheprovider -rs tests/test_fusion_kernels.py 2>&1 | tail -5 \
        | tee "$out/fusion_pytest.txt" || true ;;
    meshgt)
      for r in $MESH_RECS; do
        name=$(basename "$r")
        sed 's/^smooth = true$/smooth = false/' "$r/session.toml" > "$r/session_flat.toml"
        for g in pyrender raycast; do
          for v in session session_flat; do
            python3 -m photoreg run "$r/$v.toml" --device cuda --gbuffer $g --out "/tmp/meshgt/${name}_${g}_$v" \
              2>&1 | tail -2
            python3 -m photoreg score --composite --gt "$r" "/tmp/meshgt/${name}_${g}_$v" \
              --json "$out/meshgt_${name}_${g}_$v.json" | tail -9
          done
        done
      done ;;
    sweep)
      # The CPU rows of benchmarks/speed_error.csv are kept: copy the merged table and plot back from OUTDIR.
      [ -f "$out/speed_error.csv" ] || cp benchmarks/speed_error.csv "$out/speed_error.csv"
      python3 -m photoreg bench sweep --recordings $SWEEP_SCENES --device cuda --frames 10 \
        --voxel-sizes "${VOXELS:-0.01,0.02}" --csv "$out/speed_error.csv" --plot "$out/speed_error.png" ;;
    batch)
      OUT="$out" DATA="${DATA:-${PHOTOREG_DATA:-/tmp/data}}" bash benchmarks/batch_scale.sh ;;
    run)
      for session in sessions/tum_fr1_rpy.toml data/demo/session.toml; do   # kernels compiled before the timed runs
        python3 -m photoreg run $session --device cuda --frames 0:4 --async --out /tmp/run_warm --quiet > /dev/null
      done
      python3 benchmarks/run_ab.py "$OLD" bunny=sessions/tum_fr1_rpy.toml "bunny_async=sessions/tum_fr1_rpy.toml,--async" \
        "demo=data/demo/session.toml,--frames 0:40" "demo_async=data/demo/session.toml,--frames 0:40 --async" \
        --device cuda --frames "${RUN_FRAMES:-0:100}" --rounds "${RUN_ROUNDS:-2}" --json "$out/run_ab.json" ;;
    liveab)
      python3 -m photoreg run sessions/tum_fr1_rpy.toml --device cuda --frames 0:4 --out /tmp/run_warm --quiet > /dev/null
      python3 benchmarks/live_ab.py "$OLD" "$rec" "bunny_async=sessions/tum_fr1_rpy.toml,--async" \
        "bunny=sessions/tum_fr1_rpy.toml" "bare_async=,--async" --device cuda --meshes "$PHOTOREG_DATA/meshes" \
        --frames "${LIVE_FRAMES:-0:100}" --rounds "${LIVE_ROUNDS:-2}" --json "$out/live_ab.json"
      for mode in "" --threads; do   # where the time goes (benchmarks/live_split.py), this tree's server
        python3 -m photoreg serve --device cuda --port 8771 --meshes "$PHOTOREG_DATA/meshes" $mode > /tmp/split.log 2>&1 &
        srv=$!
        for i in $(seq 90); do grep -q "listening on" /tmp/split.log && break; sleep 1; done
        for session in sessions/tum_fr1_rpy.toml ""; do
          echo "serve $mode, ${session:-no objects}: $(python3 benchmarks/live_split.py ws://127.0.0.1:8771 "$rec" \
            ${session:+--session $session} 2>/dev/null)" | tee -a "$out/live_split.txt"
        done
        kill $srv; wait $srv || true
      done ;;
    readab)
      sed '/^\[\[objects\]\]/,/^$/d' sessions/tum_fr1_rpy.toml > /tmp/tum_bare.toml   # TUM alone
      python3 -m photoreg run sessions/tum_fr1_rpy.toml --device cuda --frames 0:4 --out /tmp/run_warm --quiet > /dev/null
      python3 benchmarks/run_ab.py "$OLD" "bare_async=/tmp/tum_bare.toml,--async" \
        "bunny_async=sessions/tum_fr1_rpy.toml,--async" --device cuda --frames "${RUN_FRAMES:-0:100}" \
        --rounds "${RUN_ROUNDS:-2}" --json "$out/read_run_ab.json"
      python3 benchmarks/live_ab.py "$OLD" "$rec" "bare_async=,--async" "bare_raw=,--async --color rgb8 --depth u16" \
        --device cuda --frames "${LIVE_FRAMES:-0:100}" --rounds "${LIVE_ROUNDS:-2}" --json "$out/read_live_ab.json" ;;
    decodeab)
      python3 -m photoreg run sessions/tum_fr1_rpy.toml --device cuda --frames 0:4 --out /tmp/run_warm --quiet > /dev/null
      python3 benchmarks/live_ab.py "$OLD" "$rec" "bare_async=,--async" "bare_raw=,--async --color rgb8 --depth u16" \
        "bare_window3=,--async --window 3" "bunny_async=sessions/tum_fr1_rpy.toml,--async" --device cuda \
        --meshes "$PHOTOREG_DATA/meshes" --frames "${LIVE_FRAMES:-0:100}" --rounds "${LIVE_ROUNDS:-2}" \
        --json "$out/decode_live_ab.json" ;;
    patchab)
      python3 -m photoreg run sessions/tum_fr1_rpy.toml --device cuda --frames 0:4 --out /tmp/run_warm --quiet > /dev/null
      python3 benchmarks/live_ab.py "$OLD" "$rec" "bunny=sessions/tum_fr1_rpy.toml" \
        "bunny_async=sessions/tum_fr1_rpy.toml,--async" \
        "bunny_raw_async=sessions/tum_fr1_rpy.toml,--async --color rgb8 --depth u16" --device cuda \
        --meshes "$PHOTOREG_DATA/meshes" --frames "${LIVE_FRAMES:-0:100}" --rounds "${LIVE_ROUNDS:-2}" \
        --json "$out/patch_live_ab.json" ;;
    serve)
      python3 benchmarks/serve_clients.py "$rec" --device cuda --clients "${SERVE_CLIENTS:-4}" \
        --frames "${SERVE_FRAMES:-0:40}" --rounds "${SERVE_ROUNDS:-1}" --json "$out/serve_clients.json" ;;
    *) echo "unknown step $step" >&2; exit 2 ;;
  esac
done
