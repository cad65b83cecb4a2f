"""predict: a detector (model_folder.LoadedModel, either backend) on every frame of a source, each frame's detections
post-processed as eval's (postprocess.postprocess), filtered by the options, and written (predict_outputs)."""
from __future__ import annotations

import logging
import time
from collections import Counter
from typing import Callable, Iterable, Iterator

import numpy as np

from stages.lib.detection.model_folder import LoadedModel
from stages.lib.detection.postprocess import postprocess, to_coco_results
from stages.lib.detection.predict_config import PredictConfig
from stages.lib.detection.predict_outputs import PredictionWriter
from stages.lib.detection.sources import Frame, Source

log = logging.getLogger(__name__)
PHASES = ("decode", "network", "post", "results", "outputs")  # where a frame's seconds go


def class_labels(names: list[str], classes: list[str] | None) -> set[int] | None:
    """The labels (1..K) of the class names kept (None: all); ValueError naming an unknown one and the classes."""
    if classes is None:
        return None
    unknown = sorted(set(classes) - set(names))
    if unknown:
        raise ValueError(f"classes {unknown} are not classes of the detector; it has {names}")
    return {names.index(name) + 1 for name in classes}


def keep(detections: dict, labels: set[int] | None, max_det: int) -> dict:
    """The detections (postprocess's, in score order) of the kept labels (None: all), at most max_det (0: all)."""
    chosen = np.ones(len(detections["scores"]), bool) if labels is None else np.isin(detections["labels"], list(labels))
    index = np.flatnonzero(chosen)[: max_det or None]
    return {name: value[index] for name, value in detections.items()}


def timed(frames: Iterable[Frame], seconds: dict[str, float]) -> Iterator[Frame]:
    """The frames, the time spent reading and decoding each added to seconds["decode"]."""
    iterator = iter(frames)
    while True:
        started = time.perf_counter()
        frame = next(iterator, None)
        seconds["decode"] += time.perf_counter() - started
        if frame is None:
            return
        yield frame


def predict_source(model: LoadedModel, source: Source, writer: PredictionWriter, options: PredictConfig,
                   progress: Callable[[Iterable, int], Iterable] = lambda frames, total: frames) -> dict:
    """Run `model` on every frame of `source` and write through `writer`; `progress(frames, total)` wraps the loop
    (a progress bar). Returns the summary: images, skipped, detections, per_class counts, seconds, images_per_second
    and seconds per phase (PHASES). An interrupted or failed call leaves predictions.partial.json and raises;
    ValueError when no frame could be read."""
    labels = class_labels(model.class_names, options.classes)
    categories = {i + 1: i + 1 for i in range(len(model.class_names))}  # category id = label
    seconds = dict.fromkeys(PHASES, 0.0)
    per_class: Counter = Counter()
    started = time.perf_counter()
    try:
        for frame in progress(timed(source.frames(), seconds), source.count):
            if frame.image is None:
                log.warning("%s: %s; skipped", frame.file_name, frame.error)
                writer.skip(frame)
                continue
            t0 = time.perf_counter()
            outputs = model.detector.outputs(frame.image)
            t1 = time.perf_counter()
            detections = keep(postprocess(outputs, model.post, model.detector_size, options.conf), labels,
                              options.max_det)
            t2 = time.perf_counter()
            results = to_coco_results(frame.image_id, detections, categories, model.post.mask_score)
            t3 = time.perf_counter()
            writer.add(frame, detections, results)
            per_class.update(model.class_names[int(label) - 1] for label in detections["labels"])
            for phase, seconds_taken in zip(PHASES[1:], (t1 - t0, t2 - t1, t3 - t2, time.perf_counter() - t3)):
                seconds[phase] += seconds_taken
    except BaseException as error:  # KeyboardInterrupt too: no predictions.json that looks complete
        writer.finish(False, error=f"{type(error).__name__}: {error}" if str(error) else type(error).__name__)
        raise
    path = writer.finish(True)
    wall = time.perf_counter() - started
    images = len(writer.images)
    if not images:
        raise ValueError(f"source {source.spec}: none of its {len(writer.skipped)} photos could be read (listed in "
                         f"{path})")
    return {"images": images, "skipped": len(writer.skipped), "detections": sum(per_class.values()),
            "per_class": {name: per_class[name] for name in model.class_names if per_class[name]},
            "seconds": wall, "images_per_second": images / wall, "seconds_per_phase": seconds, "predictions": str(path)}


def summary_line(summary: dict, out) -> str:
    """The last line of a predict call: images, skipped, detections per class, images/s and the output folder."""
    classes = ", ".join(f"{name} {count}" for name, count in summary["per_class"].items()) or "none"
    skipped = f" ({summary['skipped']} unreadable, skipped: listed in predictions.json)" if summary["skipped"] else ""
    return (f"{summary['images']} images{skipped}, {summary['detections']} detections ({classes}), "
            f"{summary['images_per_second']:.2f} images/s -> {out}")
