"""Stage dataset: a generated dataset as one folder, joined from its shards, with its card.

inputs:  `shard:<k>` (compose or cut_and_paste outputs, each images first..first+n-1 of the dataset, k in index
         order), optionally `testset` (a COCO folder whose histograms the card draws beside the dataset's).
writes:  images/ (hard links into the shards), annotations.json (ids numbered in index order, as one generator
         writing every image would), stats.json and placements.json joined, preview.png (the first shard's: the
         dataset's first images), card.md with its figures (stages/lib/cards/).
returns: the joined statistics and the number of card checks that failed; each failed check is logged as a warning
         (the run's summary lists it).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from stages.contract.errors import StageError
from stages.contract.fan_in import fanned, input_name
from stages.dataset.spec import DatasetConfig
from stages.lib.cards.page import write_card
from stages.lib.composition.shards import PREVIEW, STATS, join_placements, join_shards, join_stats, link_or_copy

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.engine.context import Context

log = logging.getLogger(__name__)


def run(ctx: Context) -> dict:
    """Join ctx.inputs' shards into ctx.out and write the dataset's card."""
    cfg = ctx.typed(DatasetConfig)
    shards = {input_name("shard", k): Path(folder) for k, folder in fanned(ctx.inputs, "shard").items()}
    if not shards:
        raise StageError(f"dataset[{ctx.item}]: no shard to join")
    dataset = join_shards(shards, ctx.out)
    stats = join_stats(shards)
    (ctx.out / STATS).write_text(json.dumps(stats, indent=2))
    record = join_placements(shards)
    if record is not None:
        record.write(ctx.out)
    first = next(iter(shards.values())) / PREVIEW
    if first.is_file():
        link_or_copy(first, ctx.out / PREVIEW)
    testset = ctx.inputs.get("testset")
    card = write_card(ctx.out, compare=Path(testset) if testset else None, samples=cfg.card_samples, seed=ctx.seed,
                      title=f"dataset[{ctx.item}]")
    for line in card.checks:
        log.warning("dataset[%s] card check: %s", ctx.item, line)
    log.info("dataset[%s]: %d images, %d instances from %d shards; card %s", ctx.item, len(dataset.images),
             len(dataset.annotations), len(shards), card.path.name)
    return {**stats, "card_checks": len(card.checks)}
