"""Docker files (issue 10), checked without a Docker engine: the Dockerfiles' instructions (COPY sources exist,
the one install script, entrypoint, port, health check), compose.yaml, .dockerignore, and scripts/install.sh
itself (bash syntax, the Debian packages FACTS.md requires). The health check command is run for real against
a `photoreg serve` process."""
from __future__ import annotations

import fnmatch
import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from servecli import free_port, serving

REPO = Path(__file__).resolve().parents[1]
DOCKER = REPO / "docker"
DOCKERFILES = {"cpu": DOCKER / "Dockerfile", "cuda": DOCKER / "Dockerfile.cuda"}
INSTALL = REPO / "scripts" / "install.sh"
PORT = "8765"


def instructions(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) per Dockerfile instruction: comments dropped, `\\` continuations joined."""
    out, pending = [], ""
    for line in path.read_text().splitlines():
        if not pending and (not line.strip() or line.lstrip().startswith("#")):
            continue
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        full = (pending + line).strip()
        pending = ""
        op, _, args = full.partition(" ")
        out.append((op.upper(), args.strip()))
    assert not pending, f"{path}: last instruction ends with a line continuation"
    return out


def args_of(path: Path, op: str) -> list[str]:
    return [a for o, a in instructions(path) if o == op]


def exec_form(args: str) -> list[str]:
    """A JSON exec-form argument list (["a", "b"]); fails on shell form."""
    value = json.loads(args)
    assert isinstance(value, list) and all(isinstance(v, str) for v in value), f"not exec form: {args}"
    return value


def healthcheck_command(path: Path) -> list[str]:
    (hc,) = args_of(path, "HEALTHCHECK")
    options, _, cmd = hc.partition("CMD ")
    assert cmd, f"{path}: HEALTHCHECK without CMD"
    assert all(o.startswith("--") for o in options.split()), f"{path}: HEALTHCHECK options {options!r}"
    return exec_form(cmd)


@pytest.mark.parametrize("kind", DOCKERFILES)
def test_dockerfile_instructions(kind):
    """FROM first; every COPY/ADD source exists; the install script runs; photoreg is the entrypoint; serve on 8765."""
    path = DOCKERFILES[kind]
    ins = instructions(path)
    assert ins[0][0] == "FROM", f"{path}: first instruction is {ins[0][0]}, not FROM"
    for op, args in ins:
        if op in ("COPY", "ADD"):
            parts = [p for p in shlex.split(args) if not p.startswith("--")]
            assert len(parts) >= 2, f"{path}: {op} {args}: needs a source and a destination"
            for src in parts[:-1]:
                assert (REPO / src).exists(), f"{path}: {op} source {src} is not in the repository"
    runs = args_of(path, "RUN")
    assert any("bash scripts/install.sh" in r for r in runs), f"{path}: no RUN of scripts/install.sh"
    assert [exec_form(a) for a in args_of(path, "ENTRYPOINT")] == [["photoreg"]]
    (cmd,) = [exec_form(a) for a in args_of(path, "CMD")]
    assert cmd[:5] == ["serve", "--host", "0.0.0.0", "--port", PORT], f"{path}: default command {cmd}"
    # objects work out of the box: the default mesh folder is the demo's, copied into the image at /app
    assert cmd[5:7] == ["--meshes", "/app/data/demo"] and ". /app" in args_of(path, "COPY")
    assert (REPO / "data" / "demo" / "object.obj").is_file()
    assert args_of(path, "EXPOSE") == [PORT]
    assert PORT in " ".join(healthcheck_command(path))


def test_base_images_and_platforms():
    """CPU: slim Python, OSMesa. CUDA: a CUDA runtime base, the CUDA Open3D build, EGL."""
    env = {k: " ".join(args_of(p, "ENV")) for k, p in DOCKERFILES.items()}
    assert re.fullmatch(r"python:3\.1[1-9]-slim(-\w+)?", args_of(DOCKERFILES["cpu"], "FROM")[0])
    assert "PYOPENGL_PLATFORM=osmesa" in env["cpu"]
    assert re.fullmatch(r"nvidia/cuda:12\.[\d.]+-runtime-ubuntu[\d.]+", args_of(DOCKERFILES["cuda"], "FROM")[0])
    assert "PYOPENGL_PLATFORM=egl" in env["cuda"]
    assert any("PHOTOREG_CUDA=1 bash scripts/install.sh" in r for r in args_of(DOCKERFILES["cuda"], "RUN"))
    assert not any("PHOTOREG_CUDA" in r for r in args_of(DOCKERFILES["cpu"], "RUN"))


def test_compose():
    """compose.yaml parses, builds docker/Dockerfile, binds 0.0.0.0 inside, publishes 8765 on loopback only,
    mounts recordings and the server's mesh folder read-only and an output volume."""
    doc = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    (svc,) = doc["services"].values()
    build = svc["build"]
    assert (DOCKER / build["context"] / build["dockerfile"]).resolve() == DOCKERFILES["cpu"]
    assert svc["command"][:5] == ["serve", "--host", "0.0.0.0", "--port", PORT]
    assert svc["ports"] == [f"127.0.0.1:{PORT}:{PORT}"]
    mounts = {}   # container path -> (source, mode); a source may hold ${VAR:-default}, so split from the right
    for v in svc["volumes"]:
        rest, mode = v.rsplit(":", 1) if v.endswith((":ro", ":rw")) else (v, "rw")
        source, target = rest.rsplit(":", 1)
        mounts[target] = (source, mode)
    assert mounts["/data"][1] == "ro", "recordings are not mounted read-only"
    assert svc["command"][5:] == ["--meshes", "/meshes"] and mounts["/meshes"][1] == "ro", "no read-only mesh folder"
    assert mounts["/out"][0] in doc["volumes"], "no named output volume at /out"
    # passed through without a value: unset on the host, unset in the container (serve refuses an empty token)
    assert svc["environment"] == ["PHOTOREG_TOKEN"]


def test_dockerignore_keeps_what_install_needs():
    """The build context keeps the sources, the install script, the packaging files and the demo."""
    patterns = [p for p in (REPO / ".dockerignore").read_text().splitlines() if p and not p.startswith("#")]
    for needed in ("pyproject.toml", "README.md", "scripts", "photoreg", "data"):
        assert not any(fnmatch.fnmatch(needed, p) for p in patterns), f".dockerignore drops {needed}"
    assert ".git" in patterns


@pytest.mark.parametrize("kind", DOCKERFILES)
def test_healthcheck_runs(kind):
    """The image's health check command succeeds against a live server and fails once it is gone."""
    port = free_port()
    cmd = [sys.executable if c == "python3" else c.replace(PORT, str(port)) for c in healthcheck_command(DOCKERFILES[kind])]
    with serving(["--host", "127.0.0.1", "--port", str(port)], port):
        assert subprocess.run(cmd, capture_output=True, timeout=30).returncode == 0
    assert subprocess.run(cmd, capture_output=True, timeout=30).returncode != 0


def test_install_script():
    """install.sh is valid bash and installs the Debian packages FACTS.md names."""
    subprocess.run(["bash", "-n", str(INSTALL)], check=True)
    debs = re.search(r'^debs="([^"]+)"', INSTALL.read_text(), re.M).group(1).split()
    for needed in ("libusb-1.0-0", "libosmesa6", "libegl1", "libegl-mesa0", "libgl1-mesa-dri", "libllvm19"):
        assert needed in debs, f"scripts/install.sh does not install {needed}"
