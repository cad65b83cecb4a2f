"""The composition's settings that the stages' specs take, light (no OpenCV): the size of a generated dataset and
its shards, which compose and cut_and_paste share (their specs extend GeneratedDataset), and the blend modes of
cut_and_paste (stages/lib/composition/blend.py)."""
from __future__ import annotations

from dataclasses import dataclass

from stages.contract.errors import StageError

# Images per generated dataset (compose and cut_and_paste): 1000 images x 4 detector epochs beat 200 x 10
# at equal detector cost (benchmarks/results/detector.md).
DATASET_IMAGES = 1000
SHARD_IMAGES = 250  # images per shard node (benchmarks/results/compose.md: the cost of loading a shard's assets)
BLEND_MODES = ("none", "gaussian", "motion", "poisson")  # blend.py's paste modes


@dataclass
class GeneratedDataset:
    """The size of a generated dataset (compose, cut_and_paste) and its shards: the pipeline makes one node per
    `shard_size` images (the last one may be smaller), each composing `num_images` images from `first_image` on,
    every image seeded by its index; the dataset stage joins them. Raising num_images computes only the new shards,
    lowering it reuses a prefix of them."""

    num_images: int = DATASET_IMAGES
    shard_size: int = SHARD_IMAGES
    first_image: int = 0  # a shard's first image index (the pipeline sets it per shard)

    def __post_init__(self) -> None:
        if self.num_images < 1 or self.shard_size < 1 or self.first_image < 0:
            raise StageError(f"need num_images >= 1, shard_size >= 1 and first_image >= 0, got {self.num_images}, "
                             f"{self.shard_size} and {self.first_image}")
