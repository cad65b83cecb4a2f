"""The capture benchmark's scoring (benchmarks/captures.py): which targets a capture meets, and the report's counts."""
from __future__ import annotations

from benchmarks.captures import meets, report

PASSING = {"seed": 2, "object": "vase", "extract_ran": True, "frames": 60, "first_attempt": 60, "registered": 60,
           "precision": 0.9514, "recall": 0.9708, "mask_iou_mean": 0.9856, "mask_iou_min": 0.9825}


def test_a_capture_meets_each_target_on_its_own():
    assert meets(PASSING) == {"extracts": True, "cut": True, "sfm_first_attempt": True}
    assert meets({**PASSING, "mask_iou_min": 0.8987})["cut"] is False  # the worst held-out view decides
    assert meets({**PASSING, "precision": 0.9499})["cut"] is False
    assert meets({**PASSING, "first_attempt": 56}) == {"extracts": True, "cut": True, "sfm_first_attempt": False}
    assert meets({**PASSING, "first_attempt": 57})["sfm_first_attempt"] is True  # 95 % of 60
    refused = {"seed": 3, "object": "plant", "frames": 60, "first_attempt": 60, "failed_stage": "extract",
               "reason": "extract: the object's base lies 25% of its height above the layer"}
    assert meets(refused) == {"extracts": False, "cut": False, "sfm_first_attempt": True}


def test_the_report_counts_the_targets_and_names_refusals():
    rows = [PASSING, {**PASSING, "object": "plant", "mask_iou_min": 0.8987},
            {**PASSING, "object": "soda_can", "first_attempt": 30, "retried": True},
            {"seed": 3, "object": "bottle", "frames": 60, "first_attempt": 60, "failed_stage": "extract",
             "reason": "extract: the object's base lies 25% of its height above the layer"}]
    text = report(rows, "python -m benchmarks.captures --seeds 2 3")
    assert "`python -m benchmarks.captures --seeds 2 3`" in text
    assert ("Of 4 captures: 3 extract (target: all); 2 have precision >= 0.95, recall >= 0.90 and held-out mask "
            "IoU >= 0.90 (target: all but one); SfM's first attempt registers >= 95 % of the frames on 3") in text
    assert "| 3 | bottle |" in text and "the object's base lies 25% of its height" in text
    assert "| 2 | soda_can | 30 / 60 / 60 | yes |" in text
    assert report(rows, "c", until="sfm").rstrip().endswith(
        "Of 4 captures: SfM's first attempt registers >= 95 % of the frames on 3 (target: all but two).")
