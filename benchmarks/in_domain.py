"""A trained detector on composed images it did not train on (in-domain), per class: how much of a class's gap on
the test photos is the domain (composed vs photographed) and how much is the detector itself.

    python -m benchmarks.in_domain MODEL_FOLDER DATASET [--images 150] [--mask-threshold 0.5] [--mask-score maskness]

MODEL_FOLDER is a train_maskrcnn cache entry (model.pt); DATASET a compose output of another seed (another
`run.seed` of the same variant: the same objects and photos, other placements). Runs the eval stage's code on the
first --images images and prints box and mask AP per class as JSON; the predictions and their preview go to a
temporary folder, whose path is printed.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
from pathlib import Path

from stages.engine.context import Context
from stages.eval import run as evaluation
from stages.eval.spec import EvalConfig
from stages.lib.detection.mask_settings import MaskScore


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("model", type=Path, help="a train_maskrcnn output folder")
    parser.add_argument("dataset", type=Path, help="a compose output folder (images/ + annotations.json)")
    parser.add_argument("--images", type=int, default=150)
    parser.add_argument("--mask-threshold", type=float, default=0.5)
    parser.add_argument("--mask-score", choices=[score.value for score in MaskScore],
                        default=EvalConfig.mask_score.value)
    args = parser.parse_args()
    params = {**dataclasses.asdict(EvalConfig()), "max_images": args.images, "mask_threshold": args.mask_threshold,
              "mask_score": args.mask_score}
    out = Path(tempfile.mkdtemp(prefix="in_domain-"))
    metrics = evaluation.run(Context(stage="eval", item="in_domain", params=params, out=out,
                                     inputs={"model": str(args.model), "testset": str(args.dataset)}))
    print(json.dumps({"model": str(args.model), "dataset": str(args.dataset), "images": metrics["images"],
                      "predictions": str(out),
                      **{kind: {"AP": round(metrics[kind]["AP"], 1),
                                "per_class": {c: round(v, 1) for c, v in metrics[kind]["per_class"].items()}}
                         for kind in ("bbox", "segm")}}, indent=1))


if __name__ == "__main__":
    main()
