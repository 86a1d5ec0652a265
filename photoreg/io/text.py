"""Text files as the readers take them (session files, recording indexes, calibration, trajectories): UTF-8, with or
without the byte-order mark Windows editors write, and an error naming the file for anything else."""
from __future__ import annotations

from pathlib import Path


def read_text(path: str | Path) -> str:
    """The file's text, a leading BOM dropped (it made line 1 unreadable: TOML's 'Invalid statement', a comment line
    taken for data); ValueError naming the file where it is not UTF-8 (before: the codec's message alone)."""
    try:
        return Path(path).read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
