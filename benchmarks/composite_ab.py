"""The composites of a session's frames by this tree and by an earlier package, compared pixel by pixel: a change
meant to leave the output alone (host-side work of the render stage) must give the same composites and shadow
ratios on the device it targets. Each package runs in a child process of its own (its folder first on the path).

usage: python benchmarks/composite_ab.py OLD SESSION.toml [FIRST:LAST] [DEVICE] [SECTION.KEY=VALUE ...]
       (OLD: a folder holding an earlier photoreg package, e.g. `git archive COMMIT photoreg | tar -x -C OLD`, or
       this tree's root to compare settings; SECTION.KEY=VALUE: session settings of this tree's run alone, e.g.
       render.gbuffer=raycast; prints one JSON object: the largest absolute difference and the pixels differing by
       more than 1e-6, and the coverage's)
"""
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve()


def composites(session: str, frames: str, device: str, out: str, *settings: str) -> None:
    """Run the session's frames in line with `settings` (SECTION.KEY=VALUE, strings) set; save every composite, shadow
    ratio and coverage (and the render stage's ms)."""
    from photoreg.config import load_session, parse_frames
    from photoreg.io.recording import iter_frames, open_configured
    from photoreg.pipeline import Pipeline

    s = load_session(session)
    s.device = device
    for setting in settings:
        key, value = setting.split("=", 1)
        section, name = key.split(".")
        setattr(getattr(s, section), name, value)
    rec = open_configured(s.recording)
    pipe = Pipeline(s, rec.intrinsics)
    comps, ratios, alphas, ms = [], [], [], []
    for f in iter_frames(rec, parse_frames(frames, len(rec))):
        r = pipe.process(f)
        comps.append(r.composite)
        ratios.append(pipe.render.last.ratio)
        alphas.append(pipe.render.last.alpha)
        ms.append(r.timings_ms["render"])
    pipe.close()
    np.savez(out, composite=np.stack(comps), ratio=np.stack(ratios), alpha=np.stack(alphas), render_ms=np.array(ms))


def main() -> None:
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    if sys.argv[1] == "--child":
        composites(*sys.argv[2:])
        return
    old, session = Path(sys.argv[1]).resolve(), str(Path(sys.argv[2]).resolve())
    frames = sys.argv[3] if len(sys.argv) > 3 else "0:8"
    device = sys.argv[4] if len(sys.argv) > 4 else "cuda"
    settings = sys.argv[5:]
    result = {"session": sys.argv[2], "frames": frames, "device": device, "settings": settings}
    with tempfile.TemporaryDirectory() as tmp:
        runs = {}
        for code, root in (("old", old), ("new", HERE.parents[1])):
            out = os.path.join(tmp, code + ".npz")
            env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
            subprocess.run([sys.executable, str(HERE), "--child", session, frames, device, out,
                            *(settings if code == "new" else [])], env=env, cwd=tmp, check=True)
            runs[code] = np.load(out)
        for key in ("composite", "ratio", "alpha"):
            d = np.abs(runs["old"][key] - runs["new"][key])
            result[key] = {"max_abs_difference": float(d.max()), "pixels_over_1e-6": int((d > 1e-6).sum())}
        for code in runs:
            result[f"render_ms_{code}"] = np.round(runs[code]["render_ms"], 2).tolist()
    print(json.dumps(result))


if __name__ == "__main__":
    main()
