"""benchmarks/gpu_job.py: the default job with one GPU as a sum of stage seconds, device stages from the GPU run
and the others from the 2-core run."""
from __future__ import annotations

import json

import pytest

from benchmarks.gpu_job import given_seconds, halving, job_rows, markdown, stage_seconds

CPU = {"sample": 160.0, "frames": 10.0, "sfm": 140.0, "splat_train": 660.0, "extract": 12.0, "bg_depth": 2.0,
       "planes": 10.0, "compose": 70.0, "dataset": 4.0, "train_maskrcnn": 1950.0, "eval": 37.0}
GPU = {"sample": 90.0, "frames": 5.0, "sfm": 60.0, "splat_train": 150.0, "extract": 8.0, "bg_depth": 1.0,
       "planes": 6.0, "compose": 40.0, "dataset": 3.0, "train_maskrcnn": 170.0, "eval": 9.0}


def test_device_stages_come_from_the_gpu_run_and_the_rest_from_the_two_cores(tmp_path):
    rows = {r["stage"]: r for r in job_rows(GPU, CPU)}
    assert {s for s, r in rows.items() if r["on"] == "GPU"} == {"splat_train", "bg_depth", "train_maskrcnn", "eval"}
    assert rows["splat_train"]["counted_s"] == 150.0 and rows["sfm"]["counted_s"] == 140.0
    total = sum(r["counted_s"] for r in rows.values())
    assert total == 150 + 1 + 170 + 9 + 160 + 10 + 140 + 12 + 10 + 70 + 4
    text = markdown(list(rows.values()), "`g.json`", tmp_path / "c.json")
    assert f"**{total:.1f}**" in text and "| sfm | 2 cores | 60.0 | 140.0 | 140.0 |" in text


def test_halving_names_the_dominant_stage_and_what_it_takes():
    rows = job_rows(GPU, CPU)
    words = halving(rows)
    assert words.startswith("train_maskrcnn dominates (170 s")  # 170 of 736 s: no single stage holds half
    assert "368 s less" in words and "(train_maskrcnn, sample, splat_train)" in words
    lopsided = job_rows({**GPU, "train_maskrcnn": 2000.0}, CPU)
    assert "train_maskrcnn at" in halving(lopsided)


def test_a_summary_without_stage_seconds_is_named(tmp_path):
    (tmp_path / "summary.json").write_text(json.dumps({"variant": "full"}))
    with pytest.raises(SystemExit, match="summary.json"):
        stage_seconds(tmp_path / "summary.json")
    with pytest.raises(SystemExit, match="eval is missing from the GPU"):
        job_rows({k: v for k, v in GPU.items() if k != "eval"}, CPU)


def test_device_seconds_can_be_given_by_stage():
    given = given_seconds(["splat_train=150", "train_maskrcnn=170.5", "eval=9", "bg_depth=1"])
    assert given == {"splat_train": 150.0, "train_maskrcnn": 170.5, "eval": 9.0, "bg_depth": 1.0}
    assert sum(r["counted_s"] for r in job_rows(given, CPU)) == 150 + 170.5 + 9 + 1 + 406
    with pytest.raises(SystemExit, match="sfm is not a stage that runs on the device"):
        given_seconds(["sfm=60"])
    with pytest.raises(SystemExit, match="STAGE=SECONDS"):
        given_seconds(["splat_train"])
