"""The root structured config: every stage's config dataclass under its group, registered with Hydra.

An unknown or mistyped key anywhere fails when Hydra composes the config, naming the key, and so does an
enumerated setting (a `choices` Enum, stages/contract/choices.py, next to its field) with another value, naming the
valid ones. A key added with `+` that the schema does not have fails `check_settings` at start, naming the
nearest valid key, and a value a stage's config refuses (out of range) fails `check_values` on the graph's nodes.
`accept_data_file` lets `data=` name a data config file anywhere.
"""
from __future__ import annotations

import dataclasses
import difflib
import hashlib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from stages.app.pipeline import GENERATORS, ORDER
from stages.bg_depth.spec import BgDepthConfig
from stages.bg_frames.spec import BgFramesConfig
from stages.compose.spec import ComposeConfig
from stages.contract.choices import choices
from stages.cut_and_paste.spec import CutAndPasteConfig
from stages.dataset.spec import DatasetConfig
from stages.engine.graph import Node, settings_problems
from stages.eval.spec import EvalConfig
from stages.extract.spec import ExtractConfig
from stages.frames.spec import FramesConfig
from stages.lib.detection.predict_config import PredictConfig
from stages.lib.device import DEVICES
from stages.lib.file_checks import DEFAULT_MAX_PIXELS
from stages.planes.spec import PlanesConfig
from stages.records.sample_layout import BACKGROUND_FOLDERS
from stages.sample.spec import SampleConfig
from stages.sfm.spec import SfmConfig
from stages.splat_train.spec import SplatTrainConfig
from stages.train_maskrcnn.spec import TrainMaskrcnnConfig

Source = choices("Source", ("sample", "folder"))  # data.source
GeneratorName = choices("GeneratorName", GENERATORS)  # variant.generator: a key of stages.app.pipeline.GENERATORS
# variant.backgrounds: generic | indomain | walk (the frames of the sample's walk through its in-domain rooms)
BackgroundKind = choices("BackgroundKind", (*BACKGROUND_FOLDERS, "walk"))
StageName = choices("StageName", ORDER)  # run.until, run.reseed
Action = choices("Action", ("run", "plan", "gc", "graph", "verify", "predict"))  # run.action (predict: stages/app/predict.py)
Device = choices("Device", DEVICES)  # run.device


@dataclass
class ObjectSpec:
    """One target object: its class name, real height in metres and (folder data) its capture, or a trained
    model of it (then frames, sfm and splat_train are skipped and extract works without cameras)."""

    name: str = MISSING
    height_m: float = MISSING
    video: Optional[str] = None  # a video file or a folder of images (data=folder)
    splat: Optional[str] = None  # instead of video: an Inria-layout .ply or a .splat file of the object
    up: Optional[list[float]] = None  # the model's up direction (objects[].splat; COLMAP frames: often [0, -1, 0]);
    #                                   None: the normal of its largest plane


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
    backgrounds, indomain_backgrounds: a folder of photos, a video (its frames chosen by bg_frames, up to
    bg_frames.count) or a list of folders and videos (checked at start: stages/app/pipeline.py background_sources).
    backgrounds: with source "sample", photos added to the sample's generic backgrounds.
    sample_backgrounds: compose on the sample's generic backgrounds (the sample stage renders them, with its
    own objects); null: with source "sample" only. false with source "sample": the sample's objects and test
    sets on the photos of `backgrounds` alone (benchmarks/mono_depth.py's degraded-depth backgrounds).
    """

    source: Source = Source.sample
    objects: list[ObjectSpec] = field(default_factory=_sample_objects)
    backgrounds: Any = None  # a path or a list of paths (OmegaConf has no union of both)
    sample_backgrounds: Optional[bool] = None
    indomain_backgrounds: Any = None
    test_sets: list[TestSetSpec] = field(
        default_factory=lambda: [TestSetSpec("test_a", "test_a"), TestSetSpec("test_b", "test_b")])
    max_backgrounds: int = 0  # 0 = all


@dataclass
class VariantConfig:
    """Which dataset a run generates, trains and evaluates (the paper's ablation axes). The variant files
    (conf/variant/*.yaml) also set the generator's own settings (compose.augment, compose.placement)."""

    name: str = "full"
    generator: GeneratorName = GeneratorName.cut_and_splat
    backgrounds: BackgroundKind = BackgroundKind.generic
    seed_as: str = ""  # the variant whose seeds this one takes: the same placements and detector draws (paired)


@dataclass
class RunConfig:
    """How the DAG runs."""

    action: Action = Action.run
    until: Optional[StageName] = None  # stop after this stage (e.g. extract); None = through eval
    cache_dir: str = "outputs/cache"  # relative to the directory dag.py was started from
    # processes for independent nodes, each with cores / workers torch threads. 2 suits a 2-core machine: two
    # splats side by side on one thread each take 300-385 s, one at a time on two threads 2 x 265 s (BENCHMARKS.md)
    workers: int = 2
    # false: a failed item, or a bad input file, leaves the rest going (datasets are made of the objects and
    # photos that remain; the summary lists what was left out); true: any failure or bad input stops the run
    strict: bool = False
    seed: int = 0
    # stages whose seeds follow `seed`; the others keep seed 0's (and its cache). None = all stages.
    reseed: Optional[list[StageName]] = None
    device: Device = Device.auto
    gc_apply: bool = False  # action=gc lists entries; true deletes them
    verify_apply: bool = False  # action=verify lists the bad cache entries (docs/cache.md); true deletes them
    # the largest image, depth map or video frame a reader accepts, in pixels (stages/lib/file_checks.py; no key holds it)
    max_image_pixels: int = DEFAULT_MAX_PIXELS
    graph_status: bool = False  # action=graph: also say how many of each stage's nodes are cached


@dataclass
class Config:
    data: DataConfig = field(default_factory=DataConfig)
    variant: VariantConfig = field(default_factory=VariantConfig)
    sample: SampleConfig = field(default_factory=SampleConfig)
    frames: FramesConfig = field(default_factory=FramesConfig)
    sfm: SfmConfig = field(default_factory=SfmConfig)
    splat_train: SplatTrainConfig = field(default_factory=SplatTrainConfig)
    extract: ExtractConfig = field(default_factory=ExtractConfig)
    bg_frames: BgFramesConfig = field(default_factory=BgFramesConfig)
    bg_depth: BgDepthConfig = field(default_factory=BgDepthConfig)
    planes: PlanesConfig = field(default_factory=PlanesConfig)
    compose: ComposeConfig = field(default_factory=ComposeConfig)
    cut_and_paste: CutAndPasteConfig = field(default_factory=CutAndPasteConfig)
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    train_maskrcnn: TrainMaskrcnnConfig = field(default_factory=TrainMaskrcnnConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    predict: PredictConfig = field(default_factory=PredictConfig)  # run.action=predict (not a stage)
    run: RunConfig = field(default_factory=RunConfig)


def register() -> None:
    """Register the root schema as `schema`; conf/config.yaml lists it first in its defaults, so
    every group file (conf/<group>/*.yaml) merges into a typed node and unknown keys fail."""
    ConfigStore.instance().store(name="schema", node=Config)


def schema_keys(schema: type = Config, prefix: str = "") -> Iterator[str]:
    """Every dotted key of the schema (a dataclass), nested dataclasses followed."""
    for name, kind in typing.get_type_hints(schema).items():
        yield prefix + name
        if dataclasses.is_dataclass(kind):
            yield from schema_keys(kind, f"{prefix}{name}.")


def unknown_keys(cfg: DictConfig, schema: type = Config, prefix: str = "") -> list[str]:
    """Dotted keys of `cfg` that the schema does not have (added with a `+` override); the free-form settings
    (dict-typed, like train_maskrcnn.cuda) are checked by their stages."""
    hints = typing.get_type_hints(schema)
    found = []
    for key in cfg.keys():
        if key not in hints:
            found.append(f"{prefix}{key}")
        elif dataclasses.is_dataclass(hints[key]) and isinstance(cfg._get_node(key), DictConfig):
            found += unknown_keys(cfg[key], hints[key], f"{prefix}{key}.")
    return found


def check_settings(cfg: DictConfig) -> None:
    """ValueError naming every key of `cfg` that is not a setting (a `+` override with a typo), each with the
    nearest valid key. The values were checked when Hydra composed the config (types and `choices`)."""
    valid = list(schema_keys())
    wrong = []
    for key in unknown_keys(cfg):
        near = difflib.get_close_matches(key, valid, n=1, cutoff=0.6)
        wrong.append(f"{key} is not a setting" + (f" (did you mean {near[0]}?)" if near else ""))
    if wrong:
        raise ValueError("unknown settings: " + "; ".join(wrong))


def check_values(nodes: list[Node]) -> None:
    """ValueError with the first value a node's settings refuse (its stage's config class: a share above 1, a
    negative radius, the dataclasses' __post_init__ in the stages' spec.py), before anything runs: the engine's one
    check of a node's settings (Node.settings), made for the nodes a run or plan needs. Types and `choices` were
    checked when Hydra composed the config, and the keys by check_settings."""
    problems = settings_problems(nodes)
    if problems:
        raise ValueError(f"invalid setting: {next(iter(problems.values()))}")


DATA_FILE_SUFFIXES = (".yaml", ".yml")
USER_DATA_DEFAULTS = {"source": "folder", "objects": [], "backgrounds": None, "sample_backgrounds": None,
                      "indomain_backgrounds": None, "test_sets": [], "max_backgrounds": 0}  # a file by path: the
#                                                            user's own data, nothing of the sample unless it says so


def user_data_node(path: Path) -> DictConfig:
    """The data option of a data config file given by path. Without `source` (or with `source: folder`) it is the
    user's own data over empty defaults (USER_DATA_DEFAULTS: no object, photo or test set of the sample; mixing in
    the sample's backgrounds is `sample_backgrounds: true`); `source: sample` adds to the sample as conf/data/*.yaml
    options do. SystemExit naming the file when it is not a YAML mapping."""
    try:
        given = OmegaConf.load(path)
    except Exception as error:  # yaml's and OmegaConf's parse errors
        raise SystemExit(f"data={path}: not a readable YAML file ({str(error).splitlines()[0]})") from None
    if not isinstance(given, DictConfig):
        raise SystemExit(f"data={path}: expected a mapping of data settings (objects, backgrounds, test_sets, ...)")
    if given.get("source", "folder") == "sample":
        return given
    return OmegaConf.merge(USER_DATA_DEFAULTS, given)


def accept_data_file(argv: list[str], conf_dir: Path, cwd: Path) -> list[str]:
    """Command-line arguments with `data=<a YAML file>` (absolute, ~, or relative to `cwd`) replaced by
    `data=<name>`, the file registered under that name as an option of the data group (user_data_node: the user's
    own data unless it says `source: sample`; its keys are checked against DataConfig like conf/data/*.yaml);
    `data=<option>.yaml` of conf/data becomes `data=<option>`. SystemExit naming the file when `data=` looks like a
    path but no such file exists."""
    out = []
    for arg in argv:
        name, _, value = arg.partition("=")
        looks_like_path = value.endswith(DATA_FILE_SUFFIXES) or "/" in value or value.startswith("~")
        if name != "data" or not looks_like_path:
            out.append(arg)
            continue
        if "/" not in value and (conf_dir / "data" / value).is_file():
            out.append(f"data={Path(value).stem}")
            continue
        path = Path(value).expanduser()
        path = path if path.is_absolute() else cwd / path
        if not path.is_file():
            options = ", ".join(sorted(p.stem for p in (conf_dir / "data").glob("*.yaml")))
            raise SystemExit(f"data={value}: no such file ({path}); give a data config file (absolute, or "
                             f"relative to {cwd}) or an option of conf/data: {options}")
        option = f"{path.stem}_{hashlib.sha256(str(path.resolve()).encode()).hexdigest()[:8]}"
        ConfigStore.instance().store(group="data", name=option, node=user_data_node(path))
        out.append(f"data={option}")
    return out
