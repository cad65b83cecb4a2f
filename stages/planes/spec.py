"""The planes stage's spec: how the horizontal placement planes of a photo (`image`) are found in its depth
(`depth`, a bg_depth folder), and how they are drawn."""
from __future__ import annotations

from dataclasses import dataclass

from stages.contract.inputs import Input, Inputs
from stages.lib.planes.search_config import PlaneSearchConfig

INPUTS = Inputs((Input("depth"), Input("image", raw="photo")))


@dataclass
class PlanesConfig(PlaneSearchConfig):
    """The plane search's settings and the drawing's."""

    dot_radius_px: int = 3                # placement.png dots
