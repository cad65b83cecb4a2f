"""Box AP of one trained detector on one test set at several inference sizes (longer side, pixels).

    python -m benchmarks.inference_size outputs/cache/train_maskrcnn/<key>/model.pt ../shared/real/plush_dog_test \
        --sizes 512 384 320 256

A diagnosis, not a setting: when a smaller size scores much higher, the test objects are larger than any
the detector saw whole in training (see benchmarks/results/detector.md, "Close-ups"). Prints one row per
size: box AP, AP50 and the number of detections; --json writes the rows.
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
from PIL import Image

from benchmarks.lib.detector_runs import add_run_arguments, start
from stages.eval.run import category_mapping, coco_metrics, predict, to_coco_results
from stages.lib.coco import load_coco
from stages.lib.detection.model import load_detector

log = logging.getLogger("benchmarks.inference_size")


def box_ap_by_size(model_file: Path, test_folder: Path, sizes: list[int], device: str = "cpu",
                   mask_threshold: float = 0.5) -> list[dict]:
    """[{"size", "AP", "AP50", "detections"}] of the detector in model_file on `device`, its input resized to
    each longer side in `sizes`; the model, the annotations and the test images are read once."""
    model, _, names = load_detector(model_file, device)
    coco_gt = load_coco(test_folder / "annotations.json")
    label_to_category = category_mapping(names, coco_gt, str(test_folder / "annotations.json"))
    image_ids = sorted(coco_gt.getImgIds())
    images = {i: np.asarray(Image.open(test_folder / "images" / coco_gt.imgs[i]["file_name"]).convert("RGB"))
              for i in image_ids}  # [H, W, 3] uint8 each
    rows = []
    for size in sizes:
        model.transform.min_size, model.transform.max_size = (size,), size
        results = [r for i in image_ids for r in to_coco_results(
            i, predict(model, images[i], device, mask_threshold), label_to_category, "box")]
        box = coco_metrics(coco_gt, results, image_ids)["bbox"]
        rows.append({"size": size, "AP": box["AP"], "AP50": box["AP50"], "detections": len(results)})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path, help="a train_maskrcnn model.pt")
    parser.add_argument("testset", type=Path, help="a COCO test folder (images/ + annotations.json)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 384, 320, 256])
    add_run_arguments(parser)
    args = parser.parse_args()
    device = start(args)
    rows = box_ap_by_size(args.model, args.testset, args.sizes, device)
    for row in rows:
        log.info("%4d px: box AP %.1f, AP50 %.1f, %d detections", row["size"], row["AP"], row["AP50"], row["detections"])
    if args.json:
        args.json.write_text(json.dumps({"model": str(args.model), "testset": str(args.testset), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
