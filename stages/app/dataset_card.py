"""`python -m stages.app.dataset_card FOLDER [--compare TESTSET] [--out DIR]`: a dataset card (card.md with its figures:
per-class counts, histograms of visible fraction, size and position, instances per image, placement kinds, what
was used and left out, labelled example images, and the checks) for any COCO dataset folder (images/ +
annotations.json): a composed dataset, a test set, another tool's. Exit 1 when a check fails."""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from stages.contract.errors import StageError
from stages.lib.cards.page import write_card


def main(argv: list[str] | None = None) -> int:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="a COCO dataset folder (images/ and annotations.json)")
    parser.add_argument("--compare", type=Path, help="a test set whose histograms are drawn beside the dataset's")
    parser.add_argument("--out", type=Path, help="where card.md and its figures go (default: the folder)")
    parser.add_argument("--samples", type=int, default=12, help="example images drawn")
    parser.add_argument("--seed", type=int, default=0, help="which example images")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        card = write_card(args.folder, args.out, args.compare, args.samples, args.seed)
    except StageError as error:
        print(f"dataset_card: {error}", file=sys.stderr)
        return 2
    for line in card.checks:
        print(f"check: {line}")
    print(f"card: {card.path}")
    return 1 if card.checks else 0


if __name__ == "__main__":
    sys.exit(main())
