"""The Cut-and-Splat graph: config in, stage nodes out (per object, per background, per variant)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from stages.bg_depth import spec as bg_depth
from stages.bg_frames import spec as bg_frames
from stages.compose import spec as compose
from stages.contract.fan_in import check_kinds, fan_in, groups, input_name
from stages.cut_and_paste import spec as cut_and_paste
from stages.dataset import spec as dataset_spec
from stages.engine.graph import Node, Ref, Stage
from stages.eval import spec as eval_spec
from stages.extract import spec as extract
from stages.frames import spec as frames
from stages.lib.capture.video_frames import VIDEO_SUFFIXES, header_frame_count
from stages.lib.depth.formats import find_sidecar_files, is_depth_sidecar
from stages.lib.depth.models import node_model
from stages.lib.imageio import IMAGE_SUFFIXES, list_images
from stages.planes import spec as planes
from stages.records import sample_layout
from stages.records.bg_frames import BgFramesRecord
from stages.sample import spec as sample
from stages.sfm import spec as sfm
from stages.splat_train import spec as splat_train
from stages.train_maskrcnn import spec as train_maskrcnn

SPECS = (sample, frames, sfm, splat_train, extract, bg_frames, bg_depth, planes, compose, cut_and_paste, dataset_spec,
         train_maskrcnn, eval_spec)
ELASTIC = {"splat_train"}  # its outputs are the same bits on any thread count (stages/engine/worker_lanes.py)
STAGES = {name: Stage(name, f"stages.{name}.run:run", spec.INPUTS,  # the stage module loads when one of its nodes runs
                      version=getattr(spec, "VERSION", "1"),  # a spec's VERSION re-keys its stage on purpose
                      elastic_threads=name in ELASTIC,
                      machine=getattr(spec, "MACHINE", ()),  # the machine facts its results depend on
                      config=getattr(spec, "".join(word.title() for word in name.split("_")) + "Config"))
          for name, spec in ((spec.__name__.split(".")[-2], spec) for spec in SPECS)}  # config: its <Name>Config
ORDER = list(STAGES)
FAN_OUT = {"frames": "object", "sfm": "object", "splat_train": "object", "extract": "object", "bg_frames": "video",
           "bg_depth": "photo", "planes": "photo", "compose": "shard", "cut_and_paste": "shard", "dataset": "variant",
           "train_maskrcnn": "variant", "eval": "test set"}  # what a stage's nodes are one per (the sample: one node)


def _generators(**generators: Stage) -> dict[str, Stage]:
    """variant.generator -> the stage that makes its dataset, checked to fan in known kinds per object and photo."""
    for stage in generators.values():
        check_kinds(stage.inputs.object_kinds, stage.inputs.photo_kinds)
    return generators


GENERATORS = _generators(cut_and_splat=STAGES["compose"], cut_and_paste=STAGES["cut_and_paste"])


@dataclass
class Graph:
    """The nodes of one configuration, by stage, and the targets a run asks for."""

    nodes: dict[str, list[Node]] = field(default_factory=dict)

    def add(self, node: Node) -> Node:
        self.nodes.setdefault(node.stage.name, []).append(node)
        return node

    def targets(self, until: str | None) -> list[Node]:
        """The last nodes to compute: those of stage `until`, else the nodes no other node reads (the evals;
        the detectors when there is no test set; the planes, which cut_and_paste does not read)."""
        if until is not None:
            return list(self.nodes.get(until, []))
        nodes = [n for stage in ORDER for n in self.nodes.get(stage, [])]
        read = {id(dep) for n in nodes for dep in n.upstream()}
        return [n for n in nodes if id(n) not in read]


def _plain(section: Any) -> dict:
    """A config section as plain JSON types (enumerated settings as their strings): a node's params."""
    if isinstance(section, DictConfig):
        return OmegaConf.to_container(section, resolve=True, enum_to_str=True)
    return dict(section)


@dataclass
class Photo:
    """A background photo and its optional sidecars (depth, intrinsics JSON): raw paths, or paths in the sample's or
    a bg_frames node's output (a video's frame slot). of_sample: one of the sample's own (views without a floor are
    expected among them)."""

    id: str
    image: Path | Ref
    sidecars: dict[str, Path | Ref]
    of_sample: bool = False


def background_sources(value: Any, key: str) -> list[str]:
    """The folders and videos a background setting (data.backgrounds, data.indomain_backgrounds) names: one path, or
    a list of them. ValueError naming the setting when it is something else."""
    if value is None:
        return []
    sources = [value] if isinstance(value, str) else list(value) if isinstance(value, (list, ListConfig)) else None
    if sources is None or not all(isinstance(source, str) and source for source in sources):
        raise ValueError(f"{key} must be a folder of photos, a video file or a list of them, got {value!r}")
    return sources


def _source_photos(graph: Graph, cfg: DictConfig, key: str, base: Path) -> list[Photo]:
    """The photos of the folders and the frame slots of the videos that the setting `key` of cfg.data names. A path
    that is no folder is taken as a video when it is a file or has a video suffix (one that cannot be read gets no
    slots: preflight names it); FileNotFoundError for any other missing path."""
    photos = []
    for source in background_sources(cfg.data[key], f"data.{key}"):
        path = Path(source) if Path(source).is_absolute() else base / source
        if path.is_dir():
            photos += _folder_photos(path)
        elif path.is_file() or path.suffix.lower() in VIDEO_SUFFIXES:
            intrinsics = {k: v for k, v in find_sidecar_files(path).items() if k == "intrinsics"}  # <stem>.json
            photos += _video_photos(graph, cfg, path.stem, {"video": path}, header_frame_count(path), intrinsics)
        else:
            raise FileNotFoundError(f"data.{key}: background folder not found: {path}")
    return photos


def _video_photos(graph: Graph, cfg: DictConfig, name: str, inputs: dict[str, Path | Ref], frames: int,
                  intrinsics: dict[str, Path | Ref], of_sample: bool = False) -> list[Photo]:
    """A background video's frame slots, min(bg_frames.count, its `frames`), known before anything runs: the
    bg_frames node that fills them (stages/bg_frames/run.py) and one photo `<name>#<k>` per slot, reading slot k's
    frame there (and its depth, when the video comes with per-frame depth). A video without frames (it cannot be
    read) gets no slot; its bg_frames node, read by nothing, still checks and names it."""
    node = graph.add(Node(STAGES["bg_frames"], name, _plain(cfg.bg_frames), inputs))
    depth = "depth" in inputs
    return [Photo(f"{name}#{k}", Ref(node, BgFramesRecord.image(k)),
                  {**({"depth": Ref(node, BgFramesRecord.depth(k))} if depth else {}), **intrinsics}, of_sample)
            for k in range(min(int(cfg.bg_frames.count), frames))]


def _sample_walk(graph: Graph, cfg: DictConfig, sample_node: Node | None) -> list[Photo]:
    """The frame slots of the sample's walk through its in-domain rooms (variant.backgrounds=walk), with the ray
    tracer's depth of each frame as its sidecar and the walk's camera as its intrinsics."""
    frames = sample_layout.walk_frames(cfg.sample)
    if sample_node is None or cfg.data.source != "sample" or not frames:
        raise ValueError("variant.backgrounds=walk composes on the frames of the sample's walk video, which needs "
                         "data.source=sample and sample.walk_seconds > 0; for your own room video, name it in "
                         "data.indomain_backgrounds and use an _indomain variant")
    inputs = {"video": Ref(sample_node, sample_layout.walk_video()),
              "depth": Ref(sample_node, sample_layout.walk_depth_folder())}
    camera = {"intrinsics": Ref(sample_node, sample_layout.walk_camera())}
    return _video_photos(graph, cfg, "walk", inputs, frames, camera, of_sample=True)


def _folder_photos(root: Path) -> list[Photo]:
    """The photos of a background folder, each with its sidecars (stages/lib/depth/formats.py)."""
    photos = []
    for image in list_images(root):
        if is_depth_sidecar(image) or ".support." in image.name:
            continue
        photos.append(Photo(image.stem, image, find_sidecar_files(image)))
    if not photos:
        raise FileNotFoundError(f"no photos ({', '.join(IMAGE_SUFFIXES)}) in background folder {root}")
    return photos


def build_graph(cfg: DictConfig, base: Path, device: str = "cpu") -> Graph:
    """All nodes for one configuration. `base` resolves relative user paths (the launch directory);
    `device` ("cpu" or "cuda") picks the splat and detector budgets, so each device has its own cache keys."""
    graph = Graph()
    data = cfg.data
    objects = [{"name": o.name, "height_m": float(o.height_m)} for o in data.objects]
    if not objects:
        raise ValueError("data.objects is empty: list each object with its name, height_m and video (a capture "
                         "video or a folder of its photos), as conf/data/folder.yaml shows")
    names = [o["name"] for o in objects]
    if len(set(names)) != len(names):
        raise ValueError(f"data.objects has duplicate names: {names}")

    sample_node = None
    if data.source == "sample":
        sample_node = graph.add(Node(STAGES["sample"], "sample", {**_plain(cfg.sample), "objects": objects}))

    per_object: dict[str, dict[str, Node]] = {}
    for spec in data.objects:
        if spec.splat or spec.up is not None:
            per_object[spec.name] = {"object": _model_object(graph, cfg, spec, sample_node, base)}
            continue
        if sample_node is not None:
            video: Path | Ref = Ref(sample_node, sample_layout.video(spec.name))
        elif spec.video:
            video = Path(spec.video) if Path(spec.video).is_absolute() else base / spec.video
        else:
            raise ValueError(f"data.objects[{spec.name}]: give its `video` (a capture) or `splat` (a trained model) "
                             "with data.source=folder")
        f = graph.add(Node(STAGES["frames"], spec.name, _plain(cfg.frames), {"video": video}))
        s = graph.add(Node(STAGES["sfm"], spec.name, _plain(cfg.sfm), {"frames": f}))
        t = graph.add(Node(STAGES["splat_train"], spec.name, splat_train.for_device(_plain(cfg.splat_train), device),
                           {"sfm": s}))
        e = graph.add(Node(STAGES["extract"], spec.name, _plain(cfg.extract), {"splat": t}))
        per_object[spec.name] = {"sfm": s, "splat": t, "object": e}

    background_sample = sample_node
    if sample_node is None and data.sample_backgrounds:  # the sample as it renders itself (its own objects)
        background_sample = graph.add(Node(STAGES["sample"], "sample", _plain(cfg.sample)))
    photos = _photos(cfg, graph, background_sample, base)
    depth_params = _plain(cfg.bg_depth)
    per_photo: dict[str, dict[str, Node | Path | Ref]] = {}
    for photo in photos:
        params, model = node_model(depth_params, "depth" in photo.sidecars, base)  # only photos it serves read it
        d = graph.add(Node(STAGES["bg_depth"], photo.id, params, {"image": photo.image, **photo.sidecars, **model}))
        p = graph.add(Node(STAGES["planes"], photo.id, _plain(cfg.planes), {"depth": d, "image": photo.image}))
        per_photo[photo.id] = {"background": photo.image, "depth": d, "planes": p}

    variant = cfg.variant
    generator = GENERATORS[variant.generator]
    _check_object_kinds(per_object, generator, variant.name)
    inputs = {**fan_in(per_object, generator.inputs.object_kinds), **fan_in(per_photo, generator.inputs.photo_kinds)}
    optional = {**groups(per_object, generator.inputs.object_kinds, "object"),  # a failed object or photo is
                **groups(per_photo, generator.inputs.photo_kinds, "photo")}  # left out, the rest is composed
    params = {**_plain(cfg[generator.name]), "objects": objects}
    if "expected_without_plane" in params:  # compose: the sample's own photos include views without a floor
        params["expected_without_plane"] = [p.id for p in photos if p.of_sample]
    seed_as = variant.seed_as or variant.name
    shards = {input_name("shard", f"{k:04d}"): graph.add(Node(generator, f"{variant.name}#{k}", shard_params,
                                                              inputs, optional, seed_item=seed_as))
              for k, shard_params in enumerate(shard_settings(params))}
    testset = {"testset": _testset(data.test_sets[0], sample_node, base)} if data.test_sets else {}
    dataset = graph.add(Node(STAGES["dataset"], variant.name, _plain(cfg.dataset), {**shards, **testset},
                             seed_item=seed_as))

    model = graph.add(Node(STAGES["train_maskrcnn"], variant.name,
                             train_maskrcnn.for_device(_plain(cfg.train_maskrcnn), device), {"dataset": dataset},
                             seed_item=seed_as))
    for test in data.test_sets:
        graph.add(Node(STAGES["eval"], f"{variant.name}@{test.name}", _plain(cfg.eval),
                       {"model": model, "testset": _testset(test, sample_node, base)},
                       seed_item=f"{seed_as}@{test.name}"))
    return graph


def _testset(test: DictConfig, sample_node: Node | None, base: Path) -> Path | Ref:
    """A test set of the data config: a folder of the sample's output, or the user's folder."""
    return Ref(sample_node, test.path) if sample_node is not None else base / test.path


def shard_settings(params: dict) -> list[dict]:
    """The settings of each shard of a generated dataset (GeneratedDataset: num_images images in shards of
    shard_size): the generator's settings with num_images and first_image of the shard, shard_size dropped, so
    that a shard's key does not depend on the dataset's size."""
    size, step = int(params["num_images"]), int(params["shard_size"])
    common = {k: v for k, v in params.items() if k not in ("num_images", "shard_size", "first_image")}
    return [{**common, "first_image": first, "num_images": min(step, size - first)} for first in range(0, size, step)]


def _model_object(graph: Graph, cfg: DictConfig, spec: DictConfig, sample_node: Node | None, base: Path) -> Node:
    """The extract node of an object given as a trained model (objects[].splat), with its up direction."""
    if sample_node is not None or spec.video or not spec.splat:
        raise ValueError(f"data.objects[{spec.name}]: `splat` (a trained model) goes with data.source=folder and "
                         "no `video`, and `up` only with `splat` (a capture's up comes from its cameras)")
    model = Path(spec.splat) if Path(spec.splat).is_absolute() else base / spec.splat
    params = {**_plain(cfg.extract), **({"up_hint": [float(v) for v in spec.up]} if spec.up is not None else {})}
    return graph.add(Node(STAGES["extract"], spec.name, params, {"model": model}))


def _check_object_kinds(per_object: dict[str, dict[str, Node]], generator: Stage, variant: str) -> None:
    """ValueError when the generator reads outputs that some objects lack (a trained model has no capture)."""
    lacking = sorted(name for name, kinds in per_object.items() if not set(generator.inputs.object_kinds) <= set(kinds))
    if lacking:
        raise ValueError(f"variant {variant}: {generator.name} needs each object's "
                         f"{', '.join(generator.inputs.object_kinds)} outputs, but {lacking} are given as trained "
                         "models (data.objects[].splat) without a capture; use a Cut-and-Splat variant, or give "
                         "their videos")


def _photos(cfg: DictConfig, graph: Graph, sample_node: Node | None, base: Path) -> list[Photo]:
    """The background photos the variant composes onto: generic ones (the sample's, when `sample_node`
    renders them, and those of data.backgrounds), in-domain ones (the sample's with data.source=sample, else
    those of data.indomain_backgrounds) or the frames of the sample's walk through its in-domain rooms. A video
    among the backgrounds adds its frame slots (bg_frames nodes, added to `graph`)."""
    for key in ("backgrounds", "indomain_backgrounds"):  # checked at start, whichever the variant uses
        background_sources(cfg.data[key], f"data.{key}")
    kind = cfg.variant.backgrounds
    if kind == "walk":
        photos = _sample_walk(graph, cfg, sample_node)
    elif kind == "indomain" and cfg.data.source == "sample":
        photos = _sample_photos(cfg, sample_node, "indomain")
    elif kind == "indomain":
        if not cfg.data.indomain_backgrounds:
            raise ValueError("data.indomain_backgrounds must name a folder of photos, a video or a list of them with "
                             "data.source=folder")
        photos = _source_photos(graph, cfg, "indomain_backgrounds", base)
    else:
        own = sample_node is not None and cfg.data.sample_backgrounds is not False  # null: the sample's own
        photos = _sample_photos(cfg, sample_node, "generic") if own else []
        photos += _source_photos(graph, cfg, "backgrounds", base)
        if not photos and not graph.nodes.get("bg_frames"):
            raise ValueError("no background photos: with data.source=folder, data.backgrounds must name a folder "
                             "of photos, a video or a list of them (or set data.sample_backgrounds=true)")
    ids = [photo.id for photo in photos]
    if len(set(ids)) != len(ids):
        raise ValueError(f"background photos with the same name: {sorted({i for i in ids if ids.count(i) > 1})}")
    limit = int(cfg.data.max_backgrounds)
    return photos[:limit] if limit > 0 else photos


def _sample_photos(cfg: DictConfig, sample_node: Node, kind: str) -> list[Photo]:
    """The sample's generic or in-domain background photos, with their depth and intrinsics sidecars."""
    return [Photo(pid, Ref(sample_node, sample_layout.photo(kind, pid)),
                  {"depth": Ref(sample_node, sample_layout.depth(kind, pid)),
                   "intrinsics": Ref(sample_node, sample_layout.intrinsics(kind, pid))}, of_sample=True)
            for pid in sample_layout.background_ids(cfg.sample, kind)]
