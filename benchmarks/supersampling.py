"""How much one sample per pixel widens a cut object's mask, by apparent size (compose's `supersample_min_side`).

    python -m benchmarks.supersampling EXTRACT_FOLDER [EXTRACT_FOLDER ...] [--heights 60 120 180 240 320]

Each EXTRACT_FOLDER is an extract cache entry (object.ply, extract.json). The object is stood upright in front of a
camera looking at it from the side, at the distance where it is HEIGHT pixels tall, and its window is rendered with
compose's own code (stages/lib/composition/render_object.py) at 1, 2 and 4 samples per pixel and axis. Each alpha > 0.5
mask (compose's instance mask) is compared with the 8x render's: IoU and area ratio. Prints one JSON line per object.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from stages.compose.run import OBJECT_PLY
from stages.engine.cache_entry import MANIFEST, read_manifest
from stages.lib.composition.render_object import object_window, render_window
from stages.lib.dataset_formats.polygons import mask_iou
from stages.lib.gaussians.model import Gaussians
from stages.lib.gaussians.ply import read_gaussians
from stages.lib.geometry import look_at_viewmat
from stages.records.extract import ExtractRecord

SAMPLES = (1, 2, 4)
REFERENCE_SAMPLES = 8


def side_view(extract: ExtractRecord, height_px: int) -> tuple[np.ndarray, np.ndarray]:
    """A camera looking horizontally at the middle of the object from 3 object heights away, focal length set so the
    object is `height_px` tall: world-to-camera viewmat [4, 4] and intrinsics K [3, 3]."""
    up, height = extract.normal, extract.height  # [3] unit, model units
    centre = extract.base_point + up * height / 2  # [3]
    side = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    distance = 3.0 * height
    viewmat = look_at_viewmat(centre + side / np.linalg.norm(side) * distance, centre, up)
    focal = height_px * distance / height
    size = 2.2 * height_px
    K = np.array([[focal, 0.0, size / 2], [0.0, focal, size / 2], [0.0, 0.0, 1.0]])
    return viewmat, K


def mask_agreement(g: Gaussians, extract: ExtractRecord, height_px: int) -> dict:
    """{samples: {"iou", "area_ratio"}} of the alpha > 0.5 mask at each of SAMPLES against REFERENCE_SAMPLES."""
    viewmat, K = side_view(extract, height_px)
    posed = g.transformed(torch.as_tensor(viewmat[:3, :3], dtype=torch.float32),
                          torch.as_tensor(viewmat[:3, 3], dtype=torch.float32))
    window = object_window(posed, K)
    masks = {s: render_window(posed, K, window, None, supersample=s)[1] > 0.5 for s in (*SAMPLES, REFERENCE_SAMPLES)}
    reference = masks[REFERENCE_SAMPLES]  # [h, w] bool
    return {s: {"iou": round(mask_iou(masks[s], reference), 3),
                "area_ratio": round(float(masks[s].sum() / max(reference.sum(), 1)), 3)} for s in SAMPLES}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("extracts", type=Path, nargs="+", help="extract cache entries (object.ply, extract.json)")
    parser.add_argument("--heights", type=int, nargs="+", default=[60, 120, 180, 240, 320])
    args = parser.parse_args()
    for folder in args.extracts:
        missing = [name for name in (OBJECT_PLY, ExtractRecord.JSON, MANIFEST) if not (folder / name).is_file()]
        if missing:
            parser.error(f"{folder} is not an extract cache entry: it has no {', '.join(missing)}")
    torch.set_num_threads(1)
    for folder in args.extracts:
        extract = ExtractRecord.read(folder)
        name = read_manifest(folder).get("item", folder.name)
        g = read_gaussians(folder / OBJECT_PLY)
        print(json.dumps({"object": name, **{f"{h}px": mask_agreement(g, extract, h) for h in args.heights}}))


if __name__ == "__main__":
    main()
