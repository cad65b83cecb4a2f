"""The Cut-and-Splat graph: config in, stage nodes out (per object, per background, per variant)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from stages import (bg_depth, compose, cut_and_paste, eval as eval_stage, extract, frames, planes, sample,
                    sfm, splat_train, train_maskrcnn)
from stages.engine import Node, Ref, Stage
from stages.depth_formats import is_depth_sidecar
from stages.fan_in import InputKinds, fan_in, groups
from stages.imageio import IMAGE_SUFFIXES, list_images
from stages.records import sample_layout

STAGES = {
    "sample": Stage("sample", sample.run),
    "frames": Stage("frames", frames.run),
    "sfm": Stage("sfm", sfm.run),
    "splat_train": Stage("splat_train", splat_train.run, elastic_threads=True),  # same bits on any thread count
    "extract": Stage("extract", extract.run),
    "bg_depth": Stage("bg_depth", bg_depth.run),
    "planes": Stage("planes", planes.run),
    "compose": Stage("compose", compose.run),
    "cut_and_paste": Stage("cut_and_paste", cut_and_paste.run),
    "train_maskrcnn": Stage("train_maskrcnn", train_maskrcnn.run),
    "eval": Stage("eval", eval_stage.run),
}
ORDER = list(STAGES)


@dataclass(frozen=True)
class Generator:
    """A dataset generator: its stage and the upstream outputs it reads (the stage module's INPUTS)."""

    stage: Stage
    inputs: InputKinds


GENERATORS = {  # variant.generator -> generator
    "cut_and_splat": Generator(STAGES["compose"], compose.INPUTS),
    "cut_and_paste": Generator(STAGES["cut_and_paste"], cut_and_paste.INPUTS),
}

def reseeded_stages(names: list[str] | None) -> tuple[str, ...] | None:
    """`run.reseed` checked against the stage names (None = every stage follows run.seed)."""
    if names is None:
        return None
    unknown = [name for name in names if name not in STAGES]
    if unknown:
        raise ValueError(f"run.reseed: unknown stage(s) {unknown}; stages are {ORDER}")
    return tuple(names)


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
            if until not in STAGES:
                raise ValueError(f"run.until={until!r} is not a stage; choose one of {ORDER}")
            return list(self.nodes.get(until, []))
        nodes = [n for stage in ORDER for n in self.nodes.get(stage, [])]
        read = {id(dep) for n in nodes for dep in n.upstream()}
        return [n for n in nodes if id(n) not in read]


def _plain(section: Any) -> dict:
    return OmegaConf.to_container(section, resolve=True) if isinstance(section, DictConfig) else dict(section)


@dataclass
class Photo:
    """A background photo and its optional sidecars (depth, intrinsics JSON): raw paths or sample paths."""

    id: str
    image: Path | Ref
    sidecars: dict[str, Path | Ref]


def _folder_photos(folder: str, base: Path) -> list[Photo]:
    root = Path(folder) if Path(folder).is_absolute() else base / folder
    if not root.is_dir():
        raise FileNotFoundError(f"background folder not found: {root}")
    photos = []
    for image in list_images(root):
        if is_depth_sidecar(image) or ".support." in image.name:
            continue
        photos.append(Photo(image.stem, image, bg_depth.find_sidecar_files(image)))
    if not photos:
        raise FileNotFoundError(f"no photos ({', '.join(IMAGE_SUFFIXES)}) in background folder {root}")
    return photos


def build_graph(cfg: DictConfig, base: Path, device: str = "cpu") -> Graph:
    """All nodes for one configuration. `base` resolves relative user paths (the launch directory);
    `device` ("cpu" or "cuda") picks the detector's budget, so each device has its own cache keys."""
    graph = Graph()
    data = cfg.data
    objects = [{"name": o.name, "height_m": float(o.height_m)} for o in data.objects]
    names = [o["name"] for o in objects]
    if len(set(names)) != len(names):
        raise ValueError(f"data.objects has duplicate names: {names}")

    sample_node = None
    if data.source == "sample":
        sample_node = graph.add(Node(STAGES["sample"], "sample", {**_plain(cfg.sample), "objects": objects}))
    elif data.source != "folder":
        raise ValueError(f"data.source must be 'sample' or 'folder', not {data.source!r}")

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
        t = graph.add(Node(STAGES["splat_train"], spec.name, _plain(cfg.splat_train), {"sfm": s}))
        e = graph.add(Node(STAGES["extract"], spec.name, _plain(cfg.extract), {"splat": t}))
        per_object[spec.name] = {"sfm": s, "splat": t, "object": e}

    background_sample = sample_node
    if sample_node is None and data.sample_backgrounds:  # the sample as it renders itself (its own objects)
        background_sample = graph.add(Node(STAGES["sample"], "sample", _plain(cfg.sample)))
    photos = _photos(cfg, background_sample, base)
    depth_params, depth_model = _plain(cfg.bg_depth), {}
    if depth_params["onnx_path"]:  # the model enters the cache key by content, not by its path
        model = Path(depth_params.pop("onnx_path"))
        depth_model = {"onnx_model": model if model.is_absolute() else base / model}
        depth_params["onnx_path"] = ""
    per_photo: dict[str, dict[str, Node | Path | Ref]] = {}
    for photo in photos:
        d = graph.add(Node(STAGES["bg_depth"], photo.id, depth_params,
                           {"image": photo.image, **photo.sidecars, **depth_model}))
        p = graph.add(Node(STAGES["planes"], photo.id, _plain(cfg.planes), {"depth": d, "image": photo.image}))
        per_photo[photo.id] = {"background": photo.image, "depth": d, "planes": p}

    variant = cfg.variant
    if variant.generator not in GENERATORS:
        raise ValueError(f"variant.generator must be one of {', '.join(GENERATORS)}, not {variant.generator!r}")
    generator = GENERATORS[variant.generator]
    _check_object_kinds(per_object, generator, variant.name)
    inputs = {**fan_in(per_object, generator.inputs.per_object), **fan_in(per_photo, generator.inputs.per_photo)}
    optional = {**groups(per_object, generator.inputs.per_object, "object"),  # a failed object or photo is
                **groups(per_photo, generator.inputs.per_photo, "photo")}  # left out, the rest is composed
    dataset = graph.add(Node(generator.stage, variant.name,
                             {**_plain(cfg[generator.stage.name]), "objects": objects}, inputs, optional))

    model = graph.add(Node(STAGES["train_maskrcnn"], variant.name,
                             train_maskrcnn.for_device(_plain(cfg.train_maskrcnn), device), {"dataset": dataset}))
    for test in data.test_sets:
        testset = Ref(sample_node, test.path) if sample_node is not None else base / test.path
        graph.add(Node(STAGES["eval"], f"{variant.name}@{test.name}", _plain(cfg.eval),
                       {"model": model, "testset": testset}))
    return graph


def _model_object(graph: Graph, cfg: DictConfig, spec: DictConfig, sample_node: Node | None, base: Path) -> Node:
    """The extract node of an object given as a trained model (objects[].splat), with its up direction."""
    if sample_node is not None or spec.video or not spec.splat:
        raise ValueError(f"data.objects[{spec.name}]: `splat` (a trained model) goes with data.source=folder and "
                         "no `video`, and `up` only with `splat` (a capture's up comes from its cameras)")
    model = Path(spec.splat) if Path(spec.splat).is_absolute() else base / spec.splat
    params = {**_plain(cfg.extract), **({"up_hint": [float(v) for v in spec.up]} if spec.up is not None else {})}
    return graph.add(Node(STAGES["extract"], spec.name, params, {"model": model}))


def _check_object_kinds(per_object: dict[str, dict[str, Node]], generator: Generator, variant: str) -> None:
    """ValueError when the generator reads outputs that some objects lack (a trained model has no capture)."""
    lacking = sorted(name for name, kinds in per_object.items() if not set(generator.inputs.per_object) <= set(kinds))
    if lacking:
        raise ValueError(f"variant {variant}: {generator.stage.name} needs each object's "
                         f"{', '.join(generator.inputs.per_object)} outputs, but {lacking} are given as trained "
                         "models (data.objects[].splat) without a capture; use a Cut-and-Splat variant, or give "
                         "their videos")


def _photos(cfg: DictConfig, sample_node: Node | None, base: Path) -> list[Photo]:
    """The background photos the variant composes onto: generic ones (the sample's, when `sample_node`
    renders them, and the photos of data.backgrounds) or in-domain ones (the sample's with
    data.source=sample, else data.indomain_backgrounds)."""
    kind = cfg.variant.backgrounds
    if kind not in ("generic", "indomain"):
        raise ValueError(f"variant.backgrounds must be generic or indomain, not {kind!r}")
    if kind == "indomain" and cfg.data.source == "sample":
        photos = _sample_photos(cfg, sample_node, "indomain")
    elif kind == "indomain":
        if not cfg.data.indomain_backgrounds:
            raise ValueError("data.indomain_backgrounds must name a folder of photos with data.source=folder")
        photos = _folder_photos(cfg.data.indomain_backgrounds, base)
    else:
        photos = _sample_photos(cfg, sample_node, "generic") if sample_node is not None else []
        photos += _folder_photos(cfg.data.backgrounds, base) if cfg.data.backgrounds else []
        if not photos:
            raise ValueError("no background photos: with data.source=folder, data.backgrounds must name a folder "
                             "of photos (or set data.sample_backgrounds=true)")
    ids = [photo.id for photo in photos]
    if len(set(ids)) != len(ids):
        raise ValueError(f"background photos with the same name: {sorted({i for i in ids if ids.count(i) > 1})}")
    limit = int(cfg.data.max_backgrounds)
    return photos[:limit] if limit > 0 else photos


def _sample_photos(cfg: DictConfig, sample_node: Node, kind: str) -> list[Photo]:
    """The sample's generic or in-domain background photos, with their depth and intrinsics sidecars."""
    return [Photo(pid, Ref(sample_node, sample_layout.photo(kind, pid)),
                  {"depth": Ref(sample_node, sample_layout.depth(kind, pid)),
                   "intrinsics": Ref(sample_node, sample_layout.intrinsics(kind, pid))})
            for pid in sample_layout.background_ids(cfg.sample, kind)]
