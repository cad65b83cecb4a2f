"""What predict writes into its output folder:

    predictions.json           {"complete": true, "model", "backend", "source", "settings", "images": [{"id",
                               "file_name", "width", "height", "frame" (videos)}], "categories": [{"id", "name"}],
                               "annotations": [COCO result records: image_id, category_id, bbox [x, y, w, h],
                               score, mask_score, segmentation (RLE)], "skipped": [{"file_name", "error"}]}
    overlays/<photo name>      each photo with its detections drawn, in the photo's own format
    overlays/<video stem>.mp4  a video's frames with their detections (OpenCV's mp4v) at the video's frame rate
    masks/<stem>_<k>_<class>.png   with masks: detection k of a photo (its k-th annotation), 0 / 255
    crops/<class>/<stem>_<k>.<ext> with crops: detection k's box cut out of the photo

predictions.json is written only when every frame is done (a temporary file renamed); an interrupted or failed call
writes predictions.partial.json instead ("complete": false), so no file named predictions.json is ever half-written.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from stages.lib.detection.overlay import draw_detections
from stages.lib.detection.predict_config import PredictConfig
from stages.lib.detection.sources import Frame, Source

PREDICTIONS, PARTIAL = "predictions.json", "predictions.partial.json"


def box_crop(image: np.ndarray, box: np.ndarray) -> np.ndarray:
    """The pixels of image [H, W, 3] covered by box [4] (x0 y0 x1 y1, outward to whole pixels, inside the image)."""
    height, width = image.shape[:2]
    x0, y0 = max(int(math.floor(box[0])), 0), max(int(math.floor(box[1])), 0)
    x1, y1 = min(int(math.ceil(box[2])), width), min(int(math.ceil(box[3])), height)
    return image[y0:max(y1, y0 + 1), x0:max(x1, x0 + 1)]


class PredictionWriter:
    """Collects what predict found on a source's frames and writes it into `out` (a new or empty folder).

    names: the class names (category id i+1 = names[i]); header: what predictions.json says about the call (model,
    backend, source, settings)."""

    def __init__(self, out: Path, source: Source, names: list[str], options: PredictConfig, header: dict):
        self.out, self.source, self.names, self.options, self.header = Path(out), source, names, options, header
        if self.out.exists() and (not self.out.is_dir() or any(self.out.iterdir())):
            raise ValueError(f"output folder {self.out}: exists and is not empty; give a new folder")
        self.images: list[dict] = []
        self.annotations: list[dict] = []
        self.skipped: list[dict] = []
        self.video: cv2.VideoWriter | None = None
        self.used_names: set[str] = set()

    def folder(self, name: str = "") -> Path:
        """The output folder, or its subfolder `name`, made when first needed."""
        path = self.out / name
        path.mkdir(parents=True, exist_ok=True)
        return path

    def skip(self, frame: Frame) -> None:
        """Record a frame that could not be read."""
        self.skipped.append({"file_name": frame.file_name, "error": frame.error})

    def add(self, frame: Frame, detections: dict, results: list[dict]) -> None:
        """Record one frame's detections (postprocess's, filtered) and their COCO records; write its overlay, masks
        and crops as the options ask."""
        height, width = frame.image.shape[:2]
        self.images.append({"id": frame.image_id, "file_name": frame.file_name, "width": width, "height": height,
                            **({"frame": frame.frame} if frame.frame is not None else {})})
        self.annotations += results
        if not (self.options.overlays or self.options.masks or self.options.crops):
            return
        stem, suffix = self._stem_and_suffix(frame)
        if self.options.overlays:
            drawn = draw_detections(frame.image, detections, self.names, 0.0, outlines=True)
            self._overlay(frame, stem + suffix, drawn)
        for k, (box, label, mask) in enumerate(zip(detections["boxes"], detections["labels"], detections["masks"])):
            name = self.names[int(label) - 1]
            if self.options.masks:
                cv2.imwrite(str(self.folder("masks") / f"{stem}_{k}_{name}.png"), mask.astype(np.uint8) * 255)
            if self.options.crops:
                Image.fromarray(box_crop(frame.image, box)).save(self.folder(f"crops/{name}") / f"{stem}_{k}{suffix}")

    def _stem_and_suffix(self, frame: Frame) -> tuple[str, str]:
        """The name of a frame's files: the photo's stem (made unique), or "<video stem>_<frame>" and .jpg."""
        path = Path(frame.file_name)
        if frame.frame is not None:
            return f"{path.stem}_{frame.frame:06d}", ".jpg"
        stem = path.stem if path.stem not in self.used_names else f"{path.stem}_{frame.image_id}"
        self.used_names.add(stem)
        return stem, path.suffix.lower()

    def _overlay(self, frame: Frame, name: str, drawn: np.ndarray) -> None:
        """Write a photo's overlay (its own format), or append a video frame's to the overlay video."""
        if frame.frame is None:
            Image.fromarray(drawn).save(self.folder("overlays") / name, **({"quality": 95} if name.endswith(
                (".jpg", ".jpeg")) else {}))
            return
        if self.video is None:
            path = self.folder("overlays") / f"{Path(frame.file_name).stem}.mp4"
            height, width = drawn.shape[:2]
            self.video = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(self.source.fps),
                                         (width, height))
            if not self.video.isOpened():
                raise RuntimeError(f"OpenCV could not open an mp4v video writer for {path}")
        self.video.write(np.ascontiguousarray(drawn[..., ::-1]))

    def finish(self, complete: bool, error: str = "") -> Path:
        """Close the overlay video and write predictions.json (complete) or predictions.partial.json (interrupted or
        failed, with `error`); returns the file written."""
        if self.video is not None:
            self.video.release()
            self.video = None
        content = {"complete": complete, **self.header, **({"error": error} if error else {}), "images": self.images,
                   "categories": [{"id": i + 1, "name": name} for i, name in enumerate(self.names)],
                   "annotations": self.annotations, "skipped": self.skipped}
        path = self.folder() / (PREDICTIONS if complete else PARTIAL)
        staging = path.with_name(path.name + ".tmp")
        staging.write_text(json.dumps(content))
        os.replace(staging, path)
        return path
