"""photoreg: photometric registration from RGB-D (README.md)."""
import os

# On a few cores a threaded BLAS only contends with the renderer and Warp (measured: solve 37 ms -> 650 ms
# on 2 cores with objects in the session; sun.score 3.4 ms -> 72 ms in a script); on many it pays (H100 host,
# 16 cores: solve 13 ms threaded, 108 ms on one thread). It must be set before numpy loads: scripts import
# photoreg first.
if (os.cpu_count() or 1) <= 4:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
