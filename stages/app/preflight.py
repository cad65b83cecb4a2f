"""Checks of the user's input files before any stage runs (`run.action=plan` and `run`).

Every raw file or folder a node reads is checked once, cheaply, by the raw kind its stage declares for that input
(stages/contract/inputs.py), with the readers the stages use: a video is
opened and its first frame decoded (a background video's header must also state its frame count), a photo folder
listed, a trained model read, a photo decoded, a depth sidecar's header read
(encoding, 16-bit, size against its photo), an intrinsics JSON parsed, a COCO test set parsed with its
category names compared with the objects of the data config and its images looked up. Inputs made by the
`sample` stage are not raw files and are not checked.

`check_inputs` returns {path: message}, each message naming the file, what is wrong and what to do; the
engine fails the nodes that read a bad file at once and leaves it out of the datasets (stages/engine/scheduler.py). The
readers are bounded (docs/bad_inputs.md: a lying header, a truncated file, NaNs, an image above the pixel limit
end in a StageError); any other exception a check raises is reported as that file's problem too, so that one
bad file never stops `plan`.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

from stages.app.pipeline import Graph
from stages.contract.errors import StageError
from stages.engine.graph import Node, Ref
from stages.lib.capture.video_frames import header_frame_count, open_video
from stages.lib.depth.formats import sidecar_format, sidecar_size
from stages.lib.depth.intrinsics import read_intrinsics_json
from stages.lib.depth.models import check_model_input
from stages.lib.gaussians.gaussian_files import check_gaussian_file
from stages.lib.imageio import IMAGE_SUFFIXES, image_size, list_images, load_photo
from stages.records.coco_dataset import CocoDataset

log = logging.getLogger(__name__)


def check_capture(path: Path, node: Node, objects: list[str]) -> None:
    """An object's video (opened, first frame decoded) or folder of photos (holds some)."""
    if path.is_dir():
        if not list_images(path):
            raise StageError(f"object capture {path}: a folder without photos ({', '.join(IMAGE_SUFFIXES)})")
        return
    check_first_frame(path, "frames", "object video")


def check_first_frame(path: Path, stage: str, role: str, frames_stated: bool = False) -> None:
    """A video opens and its first frame decodes; with `frames_stated`, its header also states a frame count."""
    capture = open_video(path, stage, role)
    try:
        if frames_stated and header_frame_count(path) == 0:
            raise StageError(f"{role} {path}: its header states no frame count, so the graph gave it no frame "
                             "slots; re-encode it as MP4 (H.264 or mp4v)")
        if not capture.read()[0]:
            raise StageError(f"{role} {path}: its first frame cannot be decoded (corrupt or truncated); "
                             "check that it plays, or re-export it")
    finally:
        capture.release()


def check_video(path: Path, node: Node, objects: list[str]) -> None:
    """A background video: it opens, its header states the frame count its frame slots were sized by
    (stages/app/pipeline.py) and its first frame decodes."""
    check_first_frame(path, node.stage.name, "background video", frames_stated=True)


def check_photo(path: Path, node: Node, objects: list[str]) -> None:
    """A background photo: decoded (a truncated file fails here) and large enough."""
    load_photo(path)


def check_depth_sidecar(path: Path, node: Node, objects: list[str]) -> None:
    """A depth sidecar of bg_depth: its encoding is known and its header gives the photo's size."""
    fmt = sidecar_format(path, node.params.get("sidecar_format", "auto"))
    width, height = sidecar_size(path, fmt)
    photo = Path(node.inputs["image"])
    photo_size = image_size(photo, "background image")
    if (width, height) != photo_size:
        raise StageError(f"depth sidecar {path}: {width}x{height} (read as {fmt}) does not match its photo {photo} "
                         f"({'x'.join(map(str, photo_size))}); it must be the photo's depth, pixel for pixel")


def check_intrinsics(path: Path, node: Node, objects: list[str]) -> None:
    """A photo's <stem>.json: JSON with a 3x3 K."""
    read_intrinsics_json(path)


def check_testset(path: Path, node: Node, objects: list[str]) -> None:
    """A COCO test set folder: it reads as a dataset (stages/records/coco_dataset.py: annotations.json parses,
    its masks fit its images, its images exist) and its categories are objects."""
    try:
        dataset = CocoDataset.read(path)
    except StageError as error:  # the message names annotations.json
        raise StageError(f"test set {error}") from error
    unknown = sorted(set(dataset.category_names) - set(objects))
    if unknown:
        raise StageError(f"test set {path / CocoDataset.JSON}: categories {unknown} are not objects of the data "
                         f"config {objects}; rename them in annotations.json or in data.objects (names must match)")


def check_model(path: Path, node: Node, objects: list[str]) -> None:
    """A trained model given for an object (objects[].splat): an Inria .ply or a .splat file that reads (all its
    values, without torch: stages/lib/gaussians/gaussian_files.py)."""
    check_gaussian_file(path)


def check_exists(path: Path, node: Node, objects: list[str]) -> None:
    """Any other raw input: it exists."""
    if not path.exists():
        raise StageError(f"{node.label}: input {path} not found; check its path in the config")


def check_depth_model(path: Path, node: Node, objects: list[str]) -> None:
    """bg_depth's model, for the photos without a sidecar: a hub model is in the Hugging Face cache or is fetched
    now, once (offline: one error naming it and how to place its files by hand); a folder holds its files; an
    .onnx file exists (stages/depth_models.check_model_input)."""
    check_model_input(path, node.params)


CHECKS: dict[str, Callable[[Path, Node, list[str]], None]] = {  # raw kind an input declares -> check
    "capture": check_capture,
    "video": check_video,
    "photo": check_photo,
    "depth_sidecar": check_depth_sidecar,
    "intrinsics": check_intrinsics,
    "testset": check_testset,
    "trained_model": check_model,
    "depth_model": check_depth_model,
    "file": check_exists,
}
FOUND_BY_CHECK = {"depth_model", "file"}  # raw kinds whose own check finds (or fetches) the files


def check_inputs(graph: Graph, objects: list[str]) -> dict[Path, str]:
    """{raw input path: what is wrong} over the raw inputs of every node of the graph (each checked once).
    objects: the object names of the data config (the categories a test set may have)."""
    problems: dict[Path, str] = {}
    checked: set[Path] = set()
    for node in (node for nodes in graph.nodes.values() for node in nodes):
        for name, value in node.inputs.items():
            if isinstance(value, (Node, Ref)) or Path(value) in checked:
                continue
            path = Path(value)
            checked.add(path)
            kind = node.stage.inputs.find(name).raw  # Node admits raw paths only where a raw kind is declared
            try:
                if kind not in FOUND_BY_CHECK:
                    check_exists(path, node, objects)
                CHECKS[kind](path, node, objects)
            except StageError as error:
                problems[path] = str(error)
            except Exception as error:  # noqa: BLE001 - a reader's bug must not stop the plan: the file is named
                log.debug("checking %s", path, exc_info=True)
                problems[path] = f"{node.label}: input {path} cannot be checked ({type(error).__name__}: {error})"
    return problems
