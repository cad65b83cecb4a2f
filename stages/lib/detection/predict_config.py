"""The settings of predict (`python dag.py run.action=predict predict.<key>=...` and `python -m stages.app.predict`'s
options): a plain dataclass (no torch), so that the config schema loads without the libraries that predict."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional


@dataclass
class PredictConfig:
    """source: a photo, a folder of photos, a glob, a video (mp4, avi, mov, mkv) or a .txt list of photos.
    out: the output folder (new or empty); None: outputs/predict/<time>/ under the folder the command started in.
    conf: the lowest box score kept. classes: the class names kept (None: all). max_det: at most this many detections
    per photo, the highest scores (0: the detector's own cap). overlays: draw the detections on each photo (a video:
    an mp4). masks: one PNG per detection (0 / 255). crops: each detection's box cut out of the photo. threads: CPU
    threads (0: all cores). export: with run.action=predict, write the config's detector as a model folder there
    (weights, model.onnx, model card), with or without a source.
    """

    source: Optional[str] = None
    out: Optional[str] = None
    conf: float = 0.5
    classes: Optional[list[str]] = None
    max_det: int = 0
    overlays: bool = True
    masks: bool = False
    crops: bool = False
    threads: int = 0
    export: Optional[str] = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.conf <= 1.0 or self.max_det < 0 or self.threads < 0:
            raise ValueError(f"predict: need 0 <= conf <= 1, max_det >= 0 and threads >= 0, got {self.conf}, "
                             f"{self.max_det} and {self.threads}")
