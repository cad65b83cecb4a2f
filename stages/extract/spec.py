"""The extract stage's spec: how the object is cut out of a trained scene (`splat`, a splat_train folder) or a given
model (`model`, objects[].splat), and how the cut is checked."""
from __future__ import annotations

from dataclasses import dataclass

from stages.contract.inputs import Input, Inputs
from stages.lib.objects.cut_config import CutConfig

MACHINE = ("cpu_kernels",)  # stages/engine/machine.py: its silhouettes are rendered with the C++ kernels
INPUTS = Inputs((Input("splat", required=False),  # a splat_train folder, or
                 Input("model", raw="trained_model", required=False)))  # a given .ply / .splat


@dataclass
class ExtractConfig(CutConfig):
    """The extract stage's settings: the cut's (CutConfig, stages/lib/objects/cut_config.py)."""
