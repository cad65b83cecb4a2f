"""The compose stage's spec: how the Cut-and-Splat dataset is made from the objects (`object:<name>`, extract
folders) and the background photos (`background:<id>`, with `depth:<id>` and `planes:<id>`), and its size,
which the Cut-and-Paste baseline shares."""
from __future__ import annotations

from dataclasses import dataclass, field

from stages.contract.choices import choices
from stages.contract.errors import StageError
from stages.contract.inputs import Input, Inputs
from stages.lib.composition.settings import GeneratedDataset
from stages.lib.gaussians.train_config import Backend

Placement = choices("Placement", ("plane", "random"))  # compose.placement: the variants full / no_placement
LightDirection = choices("LightDirection", ("photo", "random"))  # compose.light_direction
Relight = choices("Relight", ("none", "exposure", "shading"))  # compose.relight: variants relight and effects shade


MACHINE = ("cpu_kernels",)  # stages/engine/machine.py: renders the objects with the C++ kernels
INPUTS = Inputs(per_object=(Input("object"),),
                per_photo=(Input("background", raw="photo"), Input("depth"), Input("planes")))


@dataclass
class ComposeConfig(GeneratedDataset):
    """Settings of the compose stage (defaults sized for a 2-core CPU)."""

    augment: bool = True  # random SH view direction and pixel augmentations (variant no_aug: false)
    placement: Placement = Placement.plane  # plane: on placement planes | random: random poses (no_placement)
    objects: list[dict] = field(default_factory=list)  # [{"name", "height_m"}], category ids 1..n in this order
    min_objects: int = 1
    max_objects: int = 3
    random_placement_share: float = 0.0  # share of images posed at random with placement "plane" (paper: none)
    group_share: float = 0.0  # share of an image's later objects stood beside one already standing (on its plane,
    #   1 to 1 + group_spread times the sum of both footprint radii away), as objects stand in rooms, touching and
    #   hiding each other; 0: each at its own random point (the paper)
    group_spread: float = 1.0  # see group_share
    expected_without_plane: list[str] = field(default_factory=list)  # ids of photos whose having no plane is
    #   information, not a warning: the sample's own (wall close-ups, views of the ceiling); the pipeline fills it
    min_visible_fraction: float = 0.25  # drop objects with less of their alpha visible
    min_area: int = 64  # drop objects whose visible mask has fewer pixels
    mask_threshold: float = 0.5  # visible alpha above this is in the mask
    placement_attempts: int = 5  # poses tried per object before it is dropped
    apparent_height: list[float] = field(default_factory=lambda: [0.12, 0.4])  # random / non-metric size,
    #                                                                          fraction of image height
    random_depth: list[float] = field(default_factory=lambda: [2.0, 4.0])  # random poses: depth range
    depth_median_size: int = 5  # median filter of the background depth (pixels)
    depth_tolerance_rel: float = 0.03  # object pixel occluded when behind the surface by more than this
    depth_tolerance_abs: float = 0.02  # ... plus this (metres / depth units)
    max_window_fraction: float = 4.0  # reject poses whose render window exceeds this many images
    supersample_min_side: int = 160  # an object window shorter than this renders at up to 4x and is reduced by
    #   area: masks of small objects true to their coverage (0 = one sample per pixel, as before)
    image_size: list[int] | None = None  # [width, height]; None = each background's own size
    aug_blur_prob: float = 0.3
    aug_blur_sigma: float = 1.5
    aug_brightness: float = 0.15
    aug_contrast: float = 0.2
    aug_saturation: float = 0.3
    aug_hue: float = 0.03
    aug_noise_std: float = 0.03
    aug_tone_curve: float = 0.1
    # Realism beyond the paper (issue 32; stages/lib/composition/shadow.py, light.py). Both default off: over three seeds
    # of the sample they gained nothing beyond the seed spread (benchmarks/results/compose_effects.md); the variants
    # shadow, relight and effects turn them on.
    shadow: bool = False  # plane-posed objects cast a shadow on their support plane (variants shadow, effects)
    shadow_strength: list[float] = field(default_factory=lambda: [0.3, 0.7])  # darkness of a shadow's core
    #   (the light's directional share), drawn per image
    shadow_contact: float = 0.5  # darkness of the contact shadow (ambient occlusion) under an object's base
    shadow_softness: float = 0.04  # penumbra per unit of height above the plane (the light's angular radius, rad)
    shadow_depth_tolerance: float = 0.05  # a pixel takes the shadow when its depth is within this share of the
    #   plane's (+ depth_tolerance_abs): nearer surfaces (occluders) and farther ones (past the plane) do not
    light_direction: LightDirection = LightDirection.photo  # photo: azimuth towards the brighter side of the
    #   photo's planes (random when they show none) | random; the same light shades the objects
    light_elevation: list[float] = field(default_factory=lambda: [30.0, 70.0])  # degrees above the plane, per image
    #   (indoor lamps; the sample's lamps light its floors and tables from 22-68 degrees, median 40)
    relight: Relight = Relight.none  # none | exposure: exposure and white balance of the background around the
    #   object | shading: exposure, plus Lambert shading of its Gaussians by the light (variants relight, effects)
    relight_strength: float = 0.5  # how far the object's gain goes towards the background's (0 none, 1 all)
    relight_max_gain: float = 1.5  # linear gains are clamped to [1 / this, this] per channel
    relight_shading: float = 0.5  # share of the Lambert shading applied to the object's colours
    render_backend: Backend = Backend.auto
    workers: int = 0  # image processes, 0 = one per core (the files are the same for any count)
    preview_count: int = 16

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 1 <= self.min_objects <= self.max_objects:
            raise StageError(f"compose: need 1 <= min_objects <= max_objects, got {self.min_objects}, "
                             f"{self.max_objects}")
        for name, low, high in (("shadow_strength", 0.0, 0.99), ("light_elevation", 1.0, 90.0)):
            bounds = list(getattr(self, name))
            if len(bounds) != 2 or not low <= bounds[0] <= bounds[1] <= high:
                raise StageError(f"compose: {name} must be [low, high] with {low} <= low <= high <= {high}, "
                                 f"got {bounds}")
        for name in ("shadow_contact", "relight_strength", "relight_shading", "group_share"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise StageError(f"compose: {name} must be in [0, 1], got {getattr(self, name)}")
        if self.shadow_softness < 0 or self.shadow_depth_tolerance < 0 or self.relight_max_gain < 1:
            raise StageError("compose: need shadow_softness >= 0, shadow_depth_tolerance >= 0 and relight_max_gain "
                             f">= 1, got {self.shadow_softness}, {self.shadow_depth_tolerance}, "
                             f"{self.relight_max_gain}")
        if self.group_spread < 0:
            raise StageError(f"compose: group_spread must be >= 0, got {self.group_spread}")

