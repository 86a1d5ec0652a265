"""Generated benchmark recordings, made once with photoreg.synth into a cache folder and reused by
`photoreg bench sweep` and `photoreg bench renderers`."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

SCENE_CACHE = Path.home() / ".cache" / "photoreg" / "bench_scenes"


def scene_kinds(text: str) -> list[str]:
    """The scene kinds of a --scenes list (comma-separated, each once); ValueError naming the unknown ones."""
    from ..synth.scenes import SCENE_KINDS

    kinds = list(dict.fromkeys(k.strip() for k in text.split(",") if k.strip()))
    unknown = [k for k in kinds if k not in SCENE_KINDS]
    if unknown or not kinds:
        raise ValueError(f"--scenes: unknown scene kind(s) {', '.join(map(repr, unknown)) or '(none given)'}; choose "
                         f"from {', '.join(SCENE_KINDS)}")
    return kinds


def cached_scene(cache: Path, kind: str, width: int, height: int, frames: int, spp: int, camera: str = "orbit",
                 inserts: str = "none", log: Callable[[str], None] | None = None,
                 insert_mesh: str | None = None) -> Path:
    """The recording of scene `kind` with these settings in `cache` (folder named after them), rendered when missing
    (photoreg.synth.generate renders into a .partial folder and renames it: an interrupted run leaves no half scene).
    `insert_mesh`: a mesh file inserted instead of the cube (`photoreg synth --insert-mesh`; with inserts only)."""
    from ..synth.generate import SynthConfig, generate

    insert_mesh = insert_mesh if inserts != "none" else None
    name = f"{kind}-{width}x{height}-{frames}f-{spp}spp"
    name += "" if camera == "orbit" else f"-{camera}"
    name += "" if inserts == "none" else "-inserts"
    name += f"-{Path(insert_mesh).stem}" if insert_mesh else ""
    folder = Path(cache) / name
    if not (folder / "lighting_gt.json").is_file():
        if folder.exists() and any(folder.iterdir()):
            raise FileExistsError(f"{folder}: incomplete scene cache (no lighting_gt.json); remove it")
        if log:
            log(f"generating {kind} ({width}x{height}, {frames} frames, {camera} camera) into {folder}")
        generate(SynthConfig(scene=kind, out=str(folder), frames=frames, width=width, height=height, spp=spp,
                             camera=camera, insert_frames=inserts, insert_mesh=insert_mesh),
                 log=log and (lambda msg: log(f"{kind}: {msg}")))   # via .partial; the frames' progress
    elif insert_mesh:   # the folder is named after the mesh file's name alone
        made = json.loads((folder / "scene.json").read_text()).get("config", {}).get("insert_mesh")
        if made and Path(made).is_absolute() and Path(made) != Path(insert_mesh).resolve():
            raise FileExistsError(f"{folder}: cached with another mesh of that name ({made}), not {insert_mesh}; "
                                  "remove it or give another --synth-dir")
    return folder
