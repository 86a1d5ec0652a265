"""Shared test set-up: Warp kernel cache in a known folder, the shared data location, small sizes."""
from __future__ import annotations

import os
from pathlib import Path

import photoreg  # noqa: F401  (before numpy: one BLAS thread on few cores, as the CLI runs)
import pytest

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("PHOTOREG_WARP_CACHE", str(REPO / ".cache" / "warp"))
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")


def shared_data() -> Path | None:
    p = os.environ.get("PHOTOREG_DATA")
    if p and Path(p).is_dir():
        return Path(p)
    guess = REPO.parent / "shared" / "data"
    return guess if guess.is_dir() else None


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared recordings/HDR/meshes; skips with a reason when absent (CI turns that into a failure)."""
    p = shared_data()
    if p is None:
        if os.environ.get("CI"):
            pytest.fail("shared data not found in CI: PHOTOREG_DATA must point at the shared data folder")
        pytest.skip("shared data not found: set PHOTOREG_DATA to the folder holding recordings/, hdr/, meshes/")
    return p
