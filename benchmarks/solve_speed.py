"""Speed of the robust lighting solve (photoreg.lighting.robust.solve) against a git ref, on the inputs a
pipeline run gives it: same-process, alternating timings (robust to a busy machine) and the largest
relative difference of the lighting.

  python benchmarks/solve_speed.py capture RECORDING OUT.pkl [--frames 0:80:4] [--bands 3]
  python benchmarks/solve_speed.py compare OUT.pkl [--ref HEAD] [--reps 3]

`capture` runs the pipeline (CPU, stride 4, 64 rays, the session defaults otherwise) and pickles every
solve call (the frame's solve and, where a traced light is held, the joint solve with it). `compare` loads
the package at --ref (git archive into a temporary folder) next to the working tree's and times both on
every call, the ref first, each the minimum of --reps; the joint solves of the working tree get the
preceding solve as `start` where its solve takes one (as the pipeline passes it).
"""
from __future__ import annotations

import argparse
import copy
import inspect
import os
import pickle
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
import photoreg  # noqa: E402,F401  (first: its BLAS thread setting, as the CLI's, must precede numpy)

import numpy as np  # noqa: E402


def capture(args) -> int:
    import photoreg.pipeline as pl
    from photoreg.config import Session, parse_frames, validate
    from photoreg.io.recording import iter_frames, open_configured

    calls, solve = [], pl.solve

    def recording_solve(*a, **k):
        calls.append(dict(args=copy.deepcopy(a), kwargs=copy.deepcopy(k),
                          joint=any(t.name == "sun" for t in k.get("terms") or [])))
        return solve(*a, **k)

    pl.solve = recording_solve
    s = Session()
    s.recording.path, s.device, s.frames = args.recording, "cpu", args.frames
    s.lighting.stride, s.lighting.rays, s.lighting.bands = 4, 64, args.bands
    validate(s)
    rec = open_configured(s.recording)
    pipe = pl.Pipeline(s, rec.intrinsics)
    for frame in iter_frames(rec, parse_frames(s.frames, len(rec))):
        pipe.process(frame)
    for c in calls:   # the joint solve's `start` is the working tree's business, not the input's
        c["kwargs"].pop("start", None)
    with open(args.out, "wb") as f:
        pickle.dump(calls, f)
    print(f"{len(calls)} solve calls ({sum(c['joint'] for c in calls)} joint) -> {args.out}")
    return 0


def compare(args) -> int:
    from photoreg.lighting import robust as new

    tmp = tempfile.mkdtemp(prefix="solve_speed_")
    archive = subprocess.run(["git", "-C", str(REPO), "archive", args.ref, "photoreg"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
    os.rename(os.path.join(tmp, "photoreg"), os.path.join(tmp, "photoreg_ref"))
    sys.path.insert(0, tmp)
    from photoreg_ref.lighting import robust as ref  # noqa: E402  (relative imports inside: a full copy)

    with open(args.calls, "rb") as f:
        calls = pickle.load(f)
    takes_start = "start" in inspect.signature(new.solve).parameters

    def inputs(c, mod):
        kw = dict(c["kwargs"])
        if kw.get("terms"):
            kw["terms"] = [mod.Term(t.name, t.transfer, t.sh, t.upper) for t in kw["terms"]]
        return c["args"], kw

    t_ref, t_new, worst, last = [], [], 0.0, None
    for c in calls:
        (a_r, k_r), (a_n, k_n) = inputs(c, ref), inputs(c, new)
        if c["joint"] and takes_start and last is not None:
            k_n["start"] = last
        s_r, s_n = ref.solve(*a_r, **k_r), new.solve(*a_n, **k_n)
        if not c["joint"]:
            last = s_n
        F_r, F_n = s_r.lighting.sh, s_n.lighting.sh
        worst = max(worst, float(np.abs(F_n - F_r).max() / max(np.abs(F_r).max(), 1e-300)))
        best_r, best_n = np.inf, np.inf
        for _ in range(args.reps):
            t0 = time.perf_counter()
            ref.solve(*a_r, **k_r)
            t1 = time.perf_counter()
            new.solve(*a_n, **k_n)
            t2 = time.perf_counter()
            best_r, best_n = min(best_r, t1 - t0), min(best_n, t2 - t1)
        t_ref.append(best_r * 1e3)
        t_new.append(best_n * 1e3)
    t_ref, t_new = np.array(t_ref), np.array(t_new)
    print(f"{args.calls}: {len(calls)} calls; {args.ref} {t_ref.mean():.2f} ms, working tree {t_new.mean():.2f} ms "
          f"per call (min of {args.reps}); ratio {t_ref.sum() / t_new.sum():.2f} (median per call "
          f"{np.median(t_ref / t_new):.2f}); largest relative difference of F {worst:.1e}")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("capture")
    c.add_argument("recording")
    c.add_argument("out")
    c.add_argument("--frames", default="0:80:4")
    c.add_argument("--bands", type=int, default=3)
    m = sub.add_parser("compare")
    m.add_argument("calls")
    m.add_argument("--ref", default="HEAD")
    m.add_argument("--reps", type=int, default=3)
    args = ap.parse_args()
    return capture(args) if args.cmd == "capture" else compare(args)


if __name__ == "__main__":
    sys.exit(main())
