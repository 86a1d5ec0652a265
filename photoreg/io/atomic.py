"""Atomic file writes: write to a temporary file beside the target, then rename over it."""
from __future__ import annotations

import json
import math
import os
import sys
import tempfile
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temporary path in the target's folder; on success rename it onto `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + path.name + ".", suffix=suffix or path.suffix, dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; outputs get the usual permissions
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json(path: str | os.PathLike, obj) -> None:
    """obj as strict JSON (non-finite numbers, which JSON has not, written as null), atomically."""
    write_text(path, json.dumps(finite_json(obj), indent=2, allow_nan=False) + "\n")


def finite_json(obj):
    """obj with every non-finite float in its dicts, lists and tuples replaced by None."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    return obj


def check_output_dir(path: str | os.PathLike, option: str) -> None:
    """Refuse, before any work is done, an output folder's path that is a file or lies under one (`option`: the
    command-line option or key that gave it, for the message)."""
    path = Path(path)
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir():
                raise NotADirectoryError(f"output folder {path} ({option})" +
                                         (" is a file" if p == path else f": {p} is a file, not a folder"))
            return


def check_output_file(path: str | os.PathLike, option: str) -> None:
    """Refuse, before any work is done, an output file's path that is a folder or lies under a file (`option`: the
    command-line option or key that gave it, for the message)."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} ({option}) is a folder, not a file")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise NotADirectoryError(f"{path} ({option}): {parent} is a file, not a folder")
            return


def check_not_an_input(path: str | os.PathLike, option: str, inputs: dict[str, str | os.PathLike],
                       earlier: Callable[[Path], bool] = lambda _file: False) -> None:
    """Refuse, before any work is done, an output file's path (`option`: what gave it) that is an existing input file
    of the command or lies in an input folder (`inputs`: whose, e.g. "the run's", -> its path), unless earlier(file)
    says it holds this command's own earlier output: writing there would replace what the command reads."""
    target = Path(path).resolve()
    if not target.is_file():
        return
    for whose, source in inputs.items():
        source = Path(source).resolve()
        if (target == source or target.is_relative_to(source)) and not earlier(target):
            raise FileExistsError(f"{path} ({option}) is {whose} file: writing there would replace it; give another "
                                  "path")


def hold_folder(path: str | os.PathLike, option: str) -> int | None:
    """An exclusive lock on the output folder `path` (flock on the folder itself): the file descriptor to close when
    done (or the process ends); ValueError naming it (`option`: what gave it) where another process holds it, since
    two runs writing one folder would mix their files. None, with a warning on stderr, where its file system takes
    no such lock (some network file systems): the run goes on unguarded."""
    import fcntl

    fd = None
    try:
        fd = os.open(path, os.O_RDONLY)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return fd
    except BlockingIOError:
        os.close(fd)
        raise ValueError(f"output folder {path} ({option}) is in use by another run: two runs writing one folder "
                         "would mix their files (wait for it, or choose another)") from None
    except OSError as e:   # not readable, or ENOLCK, EOPNOTSUPP, ...: no locks there
        if fd is not None:
            os.close(fd)
        print(f"photoreg: warning: output folder {path} ({option}) cannot be locked ({e.strerror}): another run into "
              "it would not be refused", file=sys.stderr)
        return None

