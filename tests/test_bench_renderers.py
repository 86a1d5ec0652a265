"""`photoreg bench renderers` (issue 6): every registered renderer runs on a tiny generated insert scene and a
static one, rows land in the device's JSON and the report and plot are rebuilt from it."""
from __future__ import annotations

import json

import numpy as np
import pytest

from photoreg.bench.scenes import cached_scene
from photoreg.cli import main
from photoreg.render.registry import RENDERERS


def test_bench_renderers_tiny(tmp_path, capsys):
    pytest.importorskip("mitsuba")
    res = tmp_path / "results"
    args = ["bench", "renderers", "--size", "64x48", "--frames", "3", "--spp", "4", "--device", "cpu", "--synth-dir",
            str(tmp_path / "scenes"), "--results-dir", str(res), "--md", str(tmp_path / "r.md"), "--plot",
            str(tmp_path / "r.png")]
    rc = main(args + ["--scenes", "tabletop"])
    assert rc == 0
    run = json.loads((res / "renderers_cpu_4spp.json").read_text())
    names = {r["renderer"] for r in run["rows"]}
    assert set(RENDERERS) <= names and {f"{n}, true light" for n in RENDERERS} <= names
    for r in run["rows"]:
        assert np.isfinite([r["rmse"], r["si_rmse"]]).all()
        assert r["ms_mean"] is None or r["ms_mean"] > 0
        assert (r["flicker"] is None) == (r["renderer"].endswith("true light") or "other seeds" in r["renderer"])
        assert r["flicker"] is None or np.isfinite(r["flicker"])
    # the path tracer's own object is pasted with its noise; rendered again with other seeds it scores worse
    by = {r["renderer"]: r for r in run["rows"]}
    own, again = by["baseline: path-traced object, no shadow"], by["baseline, object path-traced with other seeds"]
    assert again["rmse"] > own["rmse"]
    # the true light changes what the renderers draw
    assert by["voxel, true light"]["rmse"] != by["voxel"]["rmse"]
    # the shadowing renderers differ from 'none' on the same frames (they do something)
    assert by["voxel"]["rmse"] != by["none"]["rmse"]
    md = (tmp_path / "r.md").read_text()
    assert f"{run['device_name']} (cpu), ground truth at 4 spp" in md
    assert all(f"| tabletop | {n} |" in md for n in RENDERERS)
    assert (tmp_path / "r.png").stat().st_size > 1000

    # another scene joins the file, the tabletop's rows kept (before: the file held the last run's scenes alone)
    # (with --results-dir alone, the report and plot go into it: before, they replaced the committed ones)
    assert main(args[:-4] + ["--scenes", " plane", "--renderers", "none"]) == 0
    rows = json.loads((res / "renderers_cpu_4spp.json").read_text())["rows"]
    assert [r for r in rows if r["scene"] == "tabletop"] == run["rows"] and any(r["scene"] == "plane" for r in rows)
    assert "| plane | none |" in (res / "renderers.md").read_text() and (res / "renderers.png").is_file()
    assert "| plane |" not in (tmp_path / "r.md").read_text()
    # refused before any work: a scene kind that does not exist, a run of another size into the file, a file that
    # is not a result
    capsys.readouterr()
    assert main(args + ["--scenes", "tabletop,bogus"]) == 2
    assert "--scenes: unknown scene kind(s) 'bogus'" in capsys.readouterr().err
    assert main([*args[:3], "32x24", *args[4:], "--scenes", "plane"]) == 2
    assert "holds a 64x48 run of 3 frames, this one is 32x24 of 3" in capsys.readouterr().err
    assert main(args + ["--scenes", "plane", "--renderers", "none,bogus"]) == 2
    assert "--renderers: unknown renderer(s) 'bogus'; choose from" in capsys.readouterr().err
    assert main([*args[:13], str(tmp_path / "r.md"), *args[14:], "--scenes", "plane"]) == 2   # --results-dir a file
    assert f"output folder {tmp_path / 'r.md'} (--results-dir) is a file" in capsys.readouterr().err
    (res / "renderers_old_1spp.json").write_text("{")
    assert main(args + ["--scenes", "plane"]) == 2
    assert f"{res / 'renderers_old_1spp.json'}: not a `photoreg bench renderers` result" in capsys.readouterr().err


def test_bench_renderers_inserted_mesh(tmp_path):
    """--insert-mesh: the generated insert scenes hold the mesh instead of the cube, and its rows go to a JSON file
    and a report section of their own."""
    pytest.importorskip("mitsuba")
    import trimesh

    mesh = tmp_path / "ico.obj"
    mesh.write_text(trimesh.exchange.obj.export_obj(trimesh.creation.icosphere(subdivisions=1)))
    res, scenes = tmp_path / "results", tmp_path / "scenes"
    rc = main(["bench", "renderers", "--scenes", "plane", "--renderers", "none,voxel", "--size", "64x48", "--frames",
               "3", "--spp", "4", "--device", "cpu", "--synth-dir", str(scenes), "--results-dir", str(res),
               "--md", str(tmp_path / "r.md"), "--plot", str(tmp_path / "r.png"), "--insert-mesh", str(mesh)])
    assert rc == 0
    run = json.loads((res / "renderers_cpu_4spp_ico.json").read_text())
    assert run["insert"] == "ico.obj" and {r["renderer"] for r in run["rows"]} >= {"none", "voxel"}
    assert "--insert-mesh" in json.loads((scenes / "plane-64x48-3f-4spp-inserts-ico" / "scene.json").read_text())[
        "command"]
    assert "ground truth at 4 spp, inserted ico.obj" in (tmp_path / "r.md").read_text()
    # another mesh of the same name is not taken for the cached scene's (the cache is named after the file's name)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "ico.obj").write_text(mesh.read_text())
    with pytest.raises(FileExistsError, match=f"cached with another mesh of that name \\({mesh}\\)"):
        cached_scene(scenes, "plane", 64, 48, 3, 4, inserts="auto", insert_mesh=str(tmp_path / "other" / "ico.obj"))
    assert cached_scene(scenes, "plane", 64, 48, 3, 4, inserts="auto", insert_mesh=str(mesh)) == \
        scenes / "plane-64x48-3f-4spp-inserts-ico"
