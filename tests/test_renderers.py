"""Renderer contract: every entry of photoreg.render.registry.RENDERERS (renderers added later included,
no edit here) runs on one real frame of the demo recording and returns well-formed Layers: shapes, alpha
and ratio in [0, 1], finite colour, a finite composite, and an object that actually shows."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from photoreg.config import load_session
from photoreg.io.recording import open_recording
from photoreg.pipeline import Pipeline
from photoreg.render.composite import Layers, composite
from photoreg.render.registry import RENDERERS

DEMO = Path(__file__).resolve().parents[1] / "data" / "demo"
FRAMES = (0, 10, 20)   # fused before the checked frame: a few views of the floor around the object


@pytest.fixture(scope="module")
def demo_input():
    """The RenderInput of the demo's third frame, from the real pipeline at a reduced stride and ray count
    (the cheap `none` renderer runs inside the pipeline; the others run on its captured input)."""
    s = load_session(DEMO / "session.toml")
    s.device, s.render.shadows = "cpu", "none"
    s.lighting.stride, s.lighting.rays = 8, 16
    rec = open_recording(s.recording.path, fmt=s.recording.format)
    pipe = Pipeline(s, rec.intrinsics)
    for i in FRAMES:
        result = pipe.process(rec.frame(i))
    assert result.composite is not None and pipe.render.last_input is not None
    return pipe.render.last_input


def test_registry_lists_the_baselines():
    assert {"voxel", "none"} <= set(RENDERERS)


@pytest.mark.parametrize("name", sorted(RENDERERS))
def test_renderer_contract(name, demo_input):
    inp = demo_input
    H, W = inp.camera.shape[:2]
    layers = RENDERERS[name](inp)
    assert isinstance(layers, Layers)
    assert layers.colour.shape == (H, W, 3) and layers.alpha.shape == (H, W) and layers.ratio.shape == (H, W, 3)
    assert np.all(np.isfinite(layers.colour)) and layers.colour.min() >= 0
    assert np.all(np.isfinite(layers.alpha)) and layers.alpha.min() >= 0 and layers.alpha.max() <= 1
    assert np.all(np.isfinite(layers.ratio)) and layers.ratio.min() >= 0 and layers.ratio.max() <= 1
    out = composite(inp.camera, layers)
    assert out.shape == (H, W, 3) and np.all(np.isfinite(out))
    obj = inp.gbuffer.coverage > 0.5
    assert obj.sum() > 50                                                    # the object is in view
    assert np.abs(out[obj] - inp.camera[obj]).mean() > 0.01 * inp.camera.mean()   # and it shows
    assert layers.colour[obj].mean() > 0                                     # lit, not black
