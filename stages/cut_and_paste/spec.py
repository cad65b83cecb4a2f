"""The cut_and_paste stage's spec: how the Cut-and-Paste baseline's dataset is made from the objects' capture
photos (`object:<name>`, `splat:<name>`, `sfm:<name>`) and the background photos (`background:<id>`)."""
from __future__ import annotations

from dataclasses import dataclass, field

from stages.contract.choices import choices
from stages.contract.errors import StageError
from stages.contract.inputs import Input, Inputs
from stages.lib.composition.settings import BLEND_MODES, GeneratedDataset
from stages.lib.gaussians.train_config import Backend

MACHINE = ("cpu_kernels",)  # stages/engine/machine.py: renders its masks with the C++ kernels
INPUTS = Inputs(per_object=(Input("object"), Input("splat"), Input("sfm")), per_photo=(Input("background", raw="photo"),))


BlendMode = choices("BlendMode", BLEND_MODES)  # cut_and_paste.blend_modes


@dataclass
class CutAndPasteConfig(GeneratedDataset):
    """Settings of the cut_and_paste stage (defaults sized for a 2-core CPU)."""

    objects: list[dict] = field(default_factory=list)  # [{"name", ...}] category ids 1..n in this order
    min_objects: int = 1
    max_objects: int = 3
    frames_per_object: int = 10  # K cut-outs per object, spread over the capture
    mask_threshold: float = 0.5  # rendered opacity above this is object
    mask_open_px: int = 3  # morphological opening of the cut-out masks
    min_cutout_pixels: int = 200
    size_range: list[float] = field(default_factory=lambda: [0.15, 0.5])  # longer side / shorter image side
    max_rotation_deg: float = 30.0
    flip_prob: float = 0.5
    blend_modes: list[BlendMode] = field(default_factory=lambda: list(BlendMode))  # one drawn per image
    min_visible_fraction: float = 0.25
    min_area: int = 64
    image_size: list[int] | None = None  # [width, height]; None = each background's own size
    render_backend: Backend = Backend.auto
    workers: int = 0  # image processes, 0 = one per core (the files are the same for any count)
    preview_count: int = 16

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.blend_modes:
            raise StageError("cut_and_paste: blend_modes is empty; give at least one")
        if not 1 <= self.min_objects <= self.max_objects:
            raise StageError(f"cut_and_paste: need 1 <= min_objects <= max_objects, got {self.min_objects}, "
                             f"{self.max_objects}")
