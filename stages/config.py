"""The root structured config: every stage's config dataclass under its group, registered with Hydra.

An unknown or mistyped key anywhere fails when Hydra composes the config, naming the key.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from stages.bg_depth import BgDepthConfig
from stages.compose import ComposeConfig
from stages.cut_and_paste import CutAndPasteConfig
from stages.eval import EvalConfig
from stages.extract import ExtractConfig
from stages.frames import FramesConfig
from stages.planes import PlanesConfig
from stages.sample import SampleConfig
from stages.sfm import SfmConfig
from stages.splat_train import SplatTrainConfig
from stages.train_maskrcnn import TrainMaskrcnnConfig


@dataclass
class ObjectSpec:
    """One target object: its class name, real height in metres and (folder data) its capture."""

    name: str = MISSING
    height_m: float = MISSING
    video: Optional[str] = None  # a video file or a folder of images (data=folder)


@dataclass
class TestSetSpec:
    """A COCO test set: a folder with images/ and annotations.json (sample: a folder in its output)."""

    name: str = MISSING
    path: str = MISSING


def _sample_objects() -> list[ObjectSpec]:
    return [ObjectSpec("bottle", 0.25), ObjectSpec("eyedrops", 0.09), ObjectSpec("plant", 0.30),
            ObjectSpec("soda_can", 0.12), ObjectSpec("vase", 0.22)]


@dataclass
class DataConfig:
    """Where objects, backgrounds and test sets come from.

    source "sample": everything from the embedded sample (rendered by the `sample` stage).
    source "folder": the user's videos (objects[].video), photos (backgrounds, with optional depth
    sidecars beside them) and COCO test sets (test_sets[].path).
    """

    source: str = "sample"
    objects: list[ObjectSpec] = field(default_factory=_sample_objects)
    backgrounds: Optional[str] = None
    indomain_backgrounds: Optional[str] = None
    test_sets: list[TestSetSpec] = field(
        default_factory=lambda: [TestSetSpec("test_a", "test_a"), TestSetSpec("test_b", "test_b")])
    max_backgrounds: int = 0  # 0 = all


@dataclass
class VariantConfig:
    """Which dataset a run generates, trains and evaluates (the paper's ablation axes). The variant files
    (conf/variant/*.yaml) also set the generator's own settings (compose.augment, compose.placement)."""

    name: str = "full"
    generator: str = "cut_and_splat"  # a key of stages.pipeline.GENERATORS: cut_and_splat | cut_and_paste
    backgrounds: str = "generic"  # generic | indomain


@dataclass
class RunConfig:
    """How the DAG runs."""

    action: str = "run"  # run | plan | gc
    until: Optional[str] = None  # stop after this stage (e.g. "extract"); None = through eval
    cache_dir: str = "outputs/cache"  # relative to the directory dag.py was started from
    workers: int = 1  # processes for independent nodes
    partial: bool = True  # keep going with independent items after a failure
    seed: int = 0
    # stages whose seeds follow `seed`; the others keep seed 0's (and its cache). None = all stages.
    reseed: Optional[list[str]] = None
    device: str = "auto"  # auto | cpu | cuda
    gc_apply: bool = False  # action=gc lists entries; true deletes them


@dataclass
class Config:
    data: DataConfig = field(default_factory=DataConfig)
    variant: VariantConfig = field(default_factory=VariantConfig)
    sample: SampleConfig = field(default_factory=SampleConfig)
    frames: FramesConfig = field(default_factory=FramesConfig)
    sfm: SfmConfig = field(default_factory=SfmConfig)
    splat_train: SplatTrainConfig = field(default_factory=SplatTrainConfig)
    extract: ExtractConfig = field(default_factory=ExtractConfig)
    bg_depth: BgDepthConfig = field(default_factory=BgDepthConfig)
    planes: PlanesConfig = field(default_factory=PlanesConfig)
    compose: ComposeConfig = field(default_factory=ComposeConfig)
    cut_and_paste: CutAndPasteConfig = field(default_factory=CutAndPasteConfig)
    detector: TrainMaskrcnnConfig = field(default_factory=TrainMaskrcnnConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    run: RunConfig = field(default_factory=RunConfig)


def register() -> None:
    """Register the root schema as `schema`; conf/config.yaml lists it first in its defaults, so
    every group file (conf/<group>/*.yaml) merges into a typed node and unknown keys fail."""
    ConfigStore.instance().store(name="schema", node=Config)
