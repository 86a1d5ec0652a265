"""Shadow renderers by name ([render] shadows): a renderer maps a RenderInput to Layers
(photoreg.render.composite). Adding a renderer is one module and one line here."""
from __future__ import annotations

from typing import Callable

from photoreg.render.composite import Layers, RenderInput
from photoreg.render.neural_shadowmap import render_neural_shadowmap
from photoreg.render.neural_soft import render_neural_soft
from photoreg.render.shadowmap import render_shadowmap
from photoreg.render.voxel import render_none, render_voxel

RENDERERS: dict[str, Callable[[RenderInput], Layers]] = {
    "voxel": render_voxel,
    "none": render_none,
    "shadowmap": render_shadowmap,
    "neural_soft": render_neural_soft,
    "neural_shadowmap": render_neural_shadowmap,
}


def get_renderer(name: str) -> Callable[[RenderInput], Layers]:
    """The renderer called `name`; ValueError listing the available ones."""
    if name not in RENDERERS:
        raise ValueError(f"render.shadows = {name!r} has no renderer yet (available: {', '.join(sorted(RENDERERS))})")
    return RENDERERS[name]
