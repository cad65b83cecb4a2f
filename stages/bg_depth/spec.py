"""The bg_depth stage's spec: where a background photo's (`image`) depth and camera come from: a sidecar file
(`depth`), an intrinsics file (`intrinsics`), a monocular depth model (`model`: a hub snapshot's config.json, a
save_pretrained folder or an .onnx file, stages/lib/depth/models.py), the settings below."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from stages.contract.choices import choices
from stages.contract.inputs import Input, Inputs
from stages.lib.depth.formats import SIDECAR_FORMATS
from stages.lib.depth.models import DEFAULT_MODEL
from stages.lib.geometry import DEFAULT_FOV_DEG

DepthProvider = choices("DepthProvider", ("sidecar", "model", "auto"))
ModelOutput = choices("ModelOutput", ("auto", "disparity", "metric_depth"))
SidecarFormat = choices("SidecarFormat", ("auto", *SIDECAR_FORMATS))


MACHINE = ("device",)  # stages/engine/machine.py: the depth model runs on the run's device
INPUTS = Inputs((Input("image", raw="photo"), Input("depth", raw="depth_sidecar", required=False),
                 Input("intrinsics", raw="intrinsics", required=False),
                 Input("model", raw="depth_model", required=False)))


@dataclass
class BgDepthConfig:
    provider: DepthProvider = DepthProvider.auto  # auto: the sidecar, else the model (bg_depth.py)
    sidecar_format: SidecarFormat = SidecarFormat.auto  # auto: from the file name (stages/lib/depth/formats.py)
    fov_deg: float = DEFAULT_FOV_DEG          # horizontal field of view when nothing else is known
    K: Optional[list] = None                  # 3x3 override for every photo
    min_side_px: int = 32                     # smaller photos are rejected
    # -- the monocular model for photos without a sidecar (stages/lib/depth/models.py), and metres from relative depth
    model: str = DEFAULT_MODEL                # metric-indoor-small | metric-outdoor-small | relative-small, a
    #                                           save_pretrained folder, an .onnx file, or none
    model_output: ModelOutput = ModelOutput.auto  # auto: from the model's config (an .onnx file: disparity)
    model_input_size: int = 518               # shorter side fed to the model (a multiple of 14)
    onnx_threads: int = 1                     # onnxruntime's threads (a transformers model uses the node's torch threads)
    camera_height_m: float = 1.4              # relative depth: the camera's height over the lowest horizontal surface
    median_depth_m: float = 2.0               # relative depth: the median depth (the scale: both priors' mean)
    max_depth_ratio: float = 20.0             # relative depth: pixels beyond this x the median depth are dropped
