"""The README doc test: every command in README.md's ```bash blocks is exercised, in README order, in one
temporary workspace (data/ linked, sessions/ copied with `frames = "0:2"`), with small settings. COMMANDS says
how each one is run; a README command missing from it fails, so a new README command needs a row here.
Docker commands are checked for consistency only (no Docker engine on CI); tests/test_docker.py checks the files."""
from __future__ import annotations

import dataclasses
import glob
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import shared_data
from photoreg.cli import build_parser
from servecli import free_port, serving

REPO = Path(__file__).resolve().parents[1]
SMALL = {"--frames": "0:2", "--rays": "8", "--bands": "3", "--quiet": None}   # 8 rays hold 3 bands (16 >= 9)
TINY_SYNTH = {"--frames": "2", "--size": "64x48", "--spp": "4"}

# README command -> (how it is run, options added or replacing the README's values).
#   ci:     not run (it is CI itself); must be one of .ci/run's commands
#   run:    `photoreg ...` as written, placeholders substituted, options applied; exit 0, --out folder written
#   serve:  started in the background on a free port (README port replaced); a WebSocket handshake must succeed
#   stream: run against that server (URL port replaced)
#   docker: not run; checked against docker/ and the README's other docker commands
COMMANDS: dict[str, tuple[str, dict]] = {
    "bash scripts/install.sh": ("ci", {}),
    ". scripts/activate.sh": ("ci", {}),
    "photoreg demo": ("run", SMALL),
    "python3 -m pytest": ("ci", {}),
    "photoreg run path/to/recording --out out/rec": ("run", SMALL),
    "photoreg run sessions/demo.toml": ("run", SMALL),
    "photoreg info path/to/recording": ("run", {}),
    "photoreg batch sessions/*.toml --workers 2 --out out/batch": ("run", {}),
    "photoreg batch sessions/*.toml --resume": ("run", {}),
    "photoreg batch sessions/*.toml --executor ray [--ray-address HOST:PORT]": ("run", {}),
    "photoreg synth tabletop --out gen/tabletop --frames 20 --size 320x240": ("run", TINY_SYNTH),
    "photoreg synth corner --out gen/corner --env $PHOTOREG_DATA/hdr/grace.hdr --yaw 30": ("run", TINY_SYNTH),
    "photoreg run gen/tabletop --out out/tabletop": ("run", SMALL),
    "photoreg score out/tabletop --gt gen/tabletop": ("run", {}),
    "photoreg serve --host 127.0.0.1 --port 8765 --meshes data/demo [--token T]": ("serve", {}),
    "photoreg stream path/to/recording --url ws://127.0.0.1:8765 --out out/stream": ("stream", SMALL),
    "photoreg stream data/demo --url ws://127.0.0.1:8765 --session data/demo/session.toml --out out/live":
        ("stream", SMALL),
    "docker build -f docker/Dockerfile -t photoreg:cpu .": ("docker", {}),
    "docker build -f docker/Dockerfile.cuda -t photoreg:cuda .": ("docker", {}),
    'docker run --rm -v "$PWD/data:/data:ro" -v "$PWD/out:/out" photoreg:cpu run /data/demo --out /out/demo':
        ("docker", {}),
    "docker run --rm --gpus all -p 127.0.0.1:8765:8765 photoreg:cuda": ("docker", {}),
    "docker compose -f docker/compose.yaml up -d --build": ("docker", {}),
    "photoreg bench sweep --scenes tabletop --size 320x240 --frames 8 --strides 4,8 --rays 16,64 --bands 3,5 "
    "--voxel-sizes 0.02":
        ("run", {"--size": "64x48", "--frames": "3", "--spp": "4", "--warmup": "1", "--strides": "8",
                 "--rays": "8", "--bands": "2", "--device": "cpu", "--synth-dir": "gen/sweep",
                 "--csv": "out/sweep.csv", "--plot": "out/sweep.png"}),
    "photoreg bench renderers --scenes tabletop,corner --size 160x120 --frames 8 --results-dir /tmp/r":
        ("run", {"--scenes": "tabletop", "--size": "64x48", "--frames": "3", "--spp": "4", "--device": "cpu",
                 "--synth-dir": "gen/bench", "--results-dir": "out/r"}),
    "photoreg bench speed path/to/recording --device cuda --stride 4 --rays 169 --bands 4":
        ("run", {"--device": "cpu", "--rays": "8", "--frames": "0:3", "--warmup": "1"}),
    "photoreg bench speed sessions/demo.toml --device cpu": ("run", {"--rays": "8", "--bands": "3", "--frames": "0:3",
                                                                    "--warmup": "1"}),
}
DOCKER_VALUE_OPTIONS = {"-v", "--volume", "-p", "--publish", "-e", "--env", "--gpus", "--name", "-f", "-t"}


def readme_commands() -> list[str]:
    """The README's ```bash blocks, one entry per command: comments dropped, `\\` continuations joined, `&&` chains
    split."""
    blocks = re.findall(r"^```bash\n(.*?)^```", (REPO / "README.md").read_text(), re.M | re.S)
    joined = [re.sub(r"\\\n\s*", "", block) for block in blocks]
    lines = [re.sub(r"\s+#.*$", "", line).strip() for block in joined for line in block.splitlines()]
    return [cmd.strip() for line in lines if line for cmd in line.split("&&")]


def ci_commands() -> list[str]:
    """The commands of .ci/run's last line."""
    last = (REPO / ".ci" / "run").read_text().strip().splitlines()[-1]
    return [c.strip() for c in last.split("&&")]


def with_options(argv: list[str], options: dict) -> list[str]:
    """argv with each option's value replaced, or the option appended (value None: a flag)."""
    argv = list(argv)
    for opt, value in options.items():
        if opt in argv:
            if value is not None:
                argv[argv.index(opt) + 1] = value
        else:
            argv += [opt] if value is None else [opt, value]
    return argv


def photoreg_argv(command: str, workspace: Path) -> list[str]:
    """The command's arguments after `photoreg`: optional [..] groups dropped, placeholders substituted, globs
    expanded in the workspace."""
    data = shared_data()
    if "$PHOTOREG_DATA" in command and data is None:
        pytest.skip("shared data not found: set PHOTOREG_DATA")
    command = re.sub(r"\s*\[[^\]]*\]", "", command).replace("path/to/recording", "data/demo")
    command = command.replace("$PHOTOREG_DATA", str(data))
    argv = []
    for arg in shlex.split(command)[1:]:
        argv += sorted(glob.glob(arg, root_dir=workspace)) if "*" in arg else [arg]
    return argv


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    """data/ linked to the repository's, sessions/ copied with `frames = "0:2"` (outputs land in the workspace)."""
    ws = tmp_path_factory.mktemp("readme")
    (ws / "data").symlink_to(REPO / "data")
    (ws / "sessions").mkdir()
    for src in sorted((REPO / "sessions").glob("*.toml")):
        text = src.read_text()
        if not re.search(r"^frames\s*=", text, re.M):
            text = 'frames = "0:2"\n' + text
        (ws / "sessions" / src.name).write_text(text)
    return ws


@pytest.fixture(scope="module")
def server(workspace):
    """The README's serve command, on a free port, for the serve and stream rows."""
    (command,) = [c for c, (how, _) in COMMANDS.items() if how == "serve"]
    port = free_port()
    argv = with_options(photoreg_argv(command, workspace), {"--port": str(port)})
    with serving(argv[1:], port) as proc:
        yield proc, port


def run_photoreg(argv: list[str], cwd: Path) -> None:
    env = dict(os.environ)
    if shared_data() is not None:
        env["PHOTOREG_DATA"] = str(shared_data())     # sessions/ reach the real recordings through it
    proc = subprocess.run([sys.executable, "-m", "photoreg", *argv], cwd=cwd, capture_output=True, text=True,
                          timeout=300, env=env)
    assert proc.returncode == 0, f"photoreg {' '.join(argv)} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}"
    if "--out" in argv:
        out = cwd / argv[argv.index("--out") + 1]
        assert out.is_dir() and any(out.iterdir()), f"photoreg {' '.join(argv)}: nothing written to {out}"


def check_docker(command: str) -> None:
    """Build: the Dockerfile exists. Run: the image is built by a README command, the port is published on
    loopback, the arguments parse as photoreg's. Compose: the file exists."""
    argv = shlex.split(command)
    if argv[1] == "build":
        assert (REPO / argv[argv.index("-f") + 1]).is_file() and argv[-1] == "."
    elif argv[1] == "run":
        i = 2
        while argv[i].startswith("-"):
            i += 2 if argv[i] in DOCKER_VALUE_OPTIONS else 1
        image, args = argv[i], argv[i + 1:]
        built = [shlex.split(c) for c in readme_commands() if c.startswith("docker build")]
        assert image in [b[b.index("-t") + 1] for b in built], f"{image} is not built by a README command"
        for opt, value in zip(argv, argv[1:]):
            if opt in ("-p", "--publish"):
                assert value.startswith("127.0.0.1:"), f"{command}: publish on loopback only"
        if args:
            build_parser().parse_args(args)
    else:
        assert argv[1:3] == ["compose", "-f"] and (REPO / argv[3]).is_file()


def test_every_readme_command_is_covered():
    """Each README command has a row in COMMANDS, and each row is still in the README."""
    readme = readme_commands()
    assert not [c for c in readme if c not in COMMANDS], "README commands without a test row (add them to COMMANDS)"
    assert not [c for c in COMMANDS if c not in readme], "COMMANDS rows no longer in the README (remove them)"


@pytest.mark.parametrize("command", readme_commands())
def test_readme_command(command, workspace, request):
    """Run (or check) one README command as COMMANDS says."""
    if command not in COMMANDS:
        pytest.fail(f"README command not covered by tests/test_readme.py COMMANDS: {command}")
    how, options = COMMANDS[command]
    if how == "ci":
        assert command in ci_commands(), f"{command!r} is not one of .ci/run's commands {ci_commands()}"
    elif how == "docker":
        check_docker(command)
    elif how == "serve":
        proc, _ = request.getfixturevalue("server")
        assert proc.poll() is None
    else:
        argv = with_options(photoreg_argv(command, workspace), options)
        if "--executor" in argv and argv[argv.index("--executor") + 1] == "ray":
            pytest.importorskip("ray", reason="the 'ray' extra is not installed")
        if how == "stream":
            _, port = request.getfixturevalue("server")
            argv = with_options(argv, {"--url": f"ws://127.0.0.1:{port}"})
        run_photoreg(argv, workspace)


def test_readme_python_examples_run():
    """Every ```python block of the README runs as written, from the repository's root (the library example)."""
    blocks = re.findall(r"```python\n(.*?)```", (REPO / "README.md").read_text(), re.S)
    assert blocks
    for code in blocks:
        out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stderr[-3000:]
        assert out.stdout.strip(), "the example prints its results"


def test_readme_session_reference_lists_every_key():
    """The README's session-file reference (its ```toml block) names every key of every section with the
    code's default, so a new or changed setting fails here until the README says so."""
    from photoreg import config

    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover
        import tomli as tomllib
    (block,) = re.findall(r"```toml\n(.*?)```", (REPO / "README.md").read_text(), re.S)
    ref = tomllib.loads(block)
    session = config.Session()
    tables = {"recording": session.recording, "reconstruction": session.reconstruction,
              "lighting": session.lighting, "render": session.render, "output": session.output}
    for name, obj in tables.items():
        want = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
        got = ref[name]
        if name == "recording":
            got = {**got, "path": ""}                       # the example names a folder; the default is empty
        assert got == want, f"README [{name}] differs from config.{type(obj).__name__}"
    obj = config.ObjectConfig()
    assert ref["objects"][0] == {**{f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)},
                                 "mesh": "object.obj"}
    assert (ref["frames"], ref["device"]) == (session.frames, session.device)
