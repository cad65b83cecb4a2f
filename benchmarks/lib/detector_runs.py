"""The command-line settings shared by the benchmarks that run one trained detector on a COCO folder
(inference_size, mask_refinement): threads, device and where the rows go."""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

import torch

from stages.lib.device import DEVICES, choose_device


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """--threads (torch CPU threads), --device and --json (a file for the rows)."""
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", choices=DEVICES, default="auto")
    parser.add_argument("--json", type=Path, help="write the rows here")


def start(args: argparse.Namespace) -> str:
    """Log to the console, set torch's threads; returns the device to run on."""
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(args.threads)
    return choose_device(args.device)
