"""The real plush dog capture, photos to cut-out with the defaults, comes out whole (issue 16): the graph of
`dag.py data=<folder config> run.until=extract` run by the engine (tests/factories/runs.py), scored
against the hand-drawn boxes of five photos (benchmarks/lib/cutout_boxes.py). About 7 minutes on one core."""
from __future__ import annotations

import pytest

from benchmarks.lib.cutout_boxes import load_boxes, score_cutout
from stages.records.sfm import SfmRecord
from tests.factories.runs import object_dirs, run_real_chain

pytestmark = [pytest.mark.heavy, pytest.mark.real]


def test_plush_dog_comes_out_whole_from_the_defaults(tmp_path, real):
    engine, graph, records = run_real_chain(tmp_path / "cache", "extract")
    assert {r.stage: r.status for r in records} == {s: "ran" for s in ("frames", "sfm", "splat_train", "extract")}
    dirs = object_dirs(engine, graph)
    sfm = SfmRecord.read(dirs["sfm"]).summary
    assert sfm["total"] == 84 and sfm["registered"] >= 0.95 * 84
    scores = score_cutout(load_boxes(real / "plush_dog" / "boxes.json"), dirs["frames"], dirs["sfm"],
                          dirs["splat_train"], dirs["extract"] / "object.ply")
    assert len(scores) == 5
    for score in scores:
        assert score.iou >= 0.85, score  # the whole dog, ears to paws
        assert score.bottom_error <= 0.04, score  # the paws are there and nothing hangs below them
        assert score.outside_fraction <= 0.02, score  # the sheet and the table do not frame the dog
