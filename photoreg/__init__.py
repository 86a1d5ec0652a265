"""photoreg: photometric registration from RGB-D (README.md)."""
import os

# One BLAS thread (unless the user sets OPENBLAS_NUM_THREADS): the solve's systems are small (K <= 28 unknowns)
# and a threaded BLAS only contends with the frames' own threads and with other processes. Measured: on 2 cores
# solve 37 ms -> 650 ms with objects in the session when threaded; on an H100 host with 16 cores (TUM stride 4)
# 23-27 frames/s in line against 20-22 threaded (with an object 14-18 against 17-18), `--async` 115-137 against
# 104-106 (32-41 against 30-33), and 8 `photoreg batch` workers sharing the GPU 21.4 frames/s in all against 12.9
# (benchmarks/gpu.md, "Many sessions on one GPU").
# It must be set before numpy loads: scripts import photoreg first, and a spawned worker imports it first too.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
