"""The sample stage's spec: the sizes of the embedded sample it renders; it reads no input."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from stages.contract.inputs import Inputs


def default_objects() -> list[dict]:
    """The five objects of the sample with their heights in metres."""
    return [{"name": "bottle", "height_m": 0.25}, {"name": "eyedrops", "height_m": 0.09},
            {"name": "plant", "height_m": 0.30}, {"name": "soda_can", "height_m": 0.12},
            {"name": "vase", "height_m": 0.22}]


INPUTS = Inputs()  # renders everything from its settings


@dataclass
class SampleConfig:
    """Sizes of the embedded sample (defaults: the full mini-benchmark).

    objects: [{"name", "height_m"}] from the object classes bottle, eyedrops, plant, soda_can, vase;
    their order fixes the COCO category ids (1..n). supersample: sub-samples per axis on geometry
    edges (1 = off). wall_closeup_fraction: share of generic backgrounds that show no horizontal
    surface. photos_per_room: generic backgrounds per room; test_rooms: rooms shared by test A,
    test B and the in-domain backgrounds. walk_seconds: length of the video walking through the test rooms (the
    in-domain rooms, one after the other, without objects) at `fps`, with per-frame depth; 0 = no walk. workers:
    rendering processes (the output does not depend on it).
    """

    seed: int = 0
    objects: list[Any] = field(default_factory=default_objects)
    width: int = 640
    height: int = 480
    num_frames: int = 60
    fps: float = 10.0
    supersample: int = 2
    num_backgrounds: int = 40
    num_indomain: int = 20
    num_test: int = 50
    wall_closeup_fraction: float = 0.15
    photos_per_room: int = 5
    test_rooms: int = 4
    walk_seconds: float = 16.0
    workers: int = 2
