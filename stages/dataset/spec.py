"""The dataset stage's spec: a generated dataset as one COCO folder, joined from its shards (`shard:<k>`, compose or
cut_and_paste outputs, k in index order), with its preview and its card, beside a test set (`testset`, the first
of the configuration's) when there is one."""
from __future__ import annotations

from dataclasses import dataclass

from stages.contract.inputs import Input, Inputs

INPUTS = Inputs((Input("testset", raw="testset", required=False),), per_shard=(Input("shard"),))


@dataclass
class DatasetConfig:
    """card_samples: example images on the card (drawn with the node's seed)."""

    card_samples: int = 12
