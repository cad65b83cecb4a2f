"""The measurement of issue 55's item 4 from sweep summaries (benchmarks/walk_backgrounds.py): walk frames against
photos and generic backgrounds with the seed spread, and the curve of box mAP against the number of walk frames."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from benchmarks.walk_backgrounds import compare, curve, filled_slots, sizes
from stages.app.summary import summarise
from stages.engine.cache_entry import MANIFEST, Outcome
from stages.lib.coco import CocoBuilder
from tests.factories.configs import compose_cfg


def write_job(sweep: Path, number: int, variant: str, ap: float, count: int = 20, filled: int | None = None) -> None:
    """One job's summary.json (one test set, test_a) in `sweep`, with its bg_frames node's metrics when `filled`."""
    job = sweep / f"{number}_{variant}"
    job.mkdir(parents=True)
    outcomes = []
    if filled is not None:
        (job / "bg_frames").mkdir()
        (job / "bg_frames" / "metrics.json").write_text(json.dumps({"filled": filled}))
        outcomes.append({"stage": "bg_frames", "status": "ran", "path": str(job / "bg_frames")})
    (job / "summary.json").write_text(json.dumps({
        "variant": {"name": variant}, "outcomes": outcomes,
        "config": {"data": {"test_sets": [{"name": "test_a", "path": "test_a"}]}, "bg_frames": {"count": count}},
        "eval": {f"{variant}@test_a": {"bbox": {"AP": ap, "AP50": ap}, "segm": {"AP": ap}}}}))


def test_walk_frames_are_compared_with_photos_and_generic_backgrounds_against_the_seed_spread(tmp_path):
    aps = {"full": (50.0, 52.0, 51.0), "full_indomain": (60.0, 61.0, 59.0), "full_walk": (59.0, 60.5, 60.0)}
    for number, (variant, seeds) in enumerate((v, s) for v, runs in aps.items() for s in runs):
        write_job(tmp_path, number, variant, seeds)
    lines = compare([tmp_path]).splitlines()
    assert "| walk frames | 3 | 59.8 ± 0.8 |" in lines
    assert "| walk frames − in-domain photos | -0.2 (0.8 / 1.0), within the spread |" in lines
    assert "| walk frames − generic backgrounds | +8.8 (0.8 / 1.0), beyond the spread |" in lines


def test_the_curve_gives_box_map_against_the_frame_count(tmp_path):
    for number, (count, ap, filled) in enumerate(((40, 58.0, 37), (5, 49.0, 5), (10, 55.0, 10))):
        write_job(tmp_path / "curve", number, "full_walk", ap, count, filled)
    for number, (variant, ap) in enumerate((("full_walk", 60.0), ("full_walk", 62.0), ("full_indomain", 70.0))):
        write_job(tmp_path / "backgrounds", number, variant, ap, 20)  # seeds of the default count, and photos
    lines = curve([tmp_path / "curve", tmp_path / "backgrounds"]).splitlines()
    assert lines[2:6] == ["| 5 | 1 | 5 | 49.0 |", "| 10 | 1 | 10 | 55.0 |", "| 20 | 2 | — | 61.0 ± 1.4 |",
                          "| 40 | 1 | 37 | 58.0 |"]
    assert (tmp_path / "curve" / "walk_frames.png").stat().st_size > 0


def test_a_sweep_run_in_parts_is_pooled(tmp_path):
    """The generic-background jobs from one sweep folder, the walk's from another: one comparison."""
    for number, ap in enumerate((50.0, 52.0, 51.0)):
        write_job(tmp_path / "ablation", number, "full", ap)
        write_job(tmp_path / "walk", number, "full_walk", ap + 9)
    lines = compare([tmp_path / "walk", tmp_path / "ablation"]).splitlines()
    assert "| generic backgrounds | 3 | 51.0 ± 1.0 |" in lines and "| walk frames | 3 | 60.0 ± 1.0 |" in lines
    assert "| walk frames − generic backgrounds | +9.0 (1.0 / 1.0), beyond the spread |" in lines


def test_a_summary_written_before_outcomes_is_still_read(tmp_path):
    """Summaries before 2026-11-28 listed the nodes under "records"; a sweep's report still finds them."""
    (tmp_path / "metrics.json").write_text(json.dumps({"filled": 17}))
    node = {"stage": "bg_frames", "status": "cached", "path": str(tmp_path)}
    assert filled_slots({"records": [node]}) == filled_slots({"outcomes": [node]}) == 17
    assert filled_slots({}) is None


def test_an_archived_summary_still_tells_the_filled_slots(tmp_path):
    """The summary keeps the bg_frames node's metrics: once the cache entry is gone (only the sweep's summary.json
    files are archived), the slots the walk filled are still read."""
    entry = tmp_path / "cache" / "bg_frames"
    entry.mkdir(parents=True)
    (entry / "metrics.json").write_text(json.dumps({"slots": 20, "filled": 18}))
    (entry / MANIFEST).write_text(json.dumps({"seconds": 1.0}))
    summary = summarise([Outcome("bg_frames", "walk", "k", "cached", path=str(entry))], compose_cfg([]), {}, [])
    shutil.rmtree(tmp_path / "cache")
    assert filled_slots(json.loads(json.dumps(summary))) == 18


def write_squares(folder: Path, sides: list[int], top: int) -> Path:
    """A COCO folder of one 100x100 image with a square instance of each side (pixels), their top edge at row `top`."""
    (folder / "images").mkdir(parents=True)
    Image.fromarray(np.zeros((100, 100, 3), np.uint8)).save(folder / "images" / "0000.png")
    builder = CocoBuilder(["square"])
    image_id = builder.add_image("0000.png", 100, 100)
    for side in sides:
        mask = np.zeros((100, 100), bool)
        mask[top:top + side, :side] = True
        builder.add_instance(image_id, 1, mask)
    builder.dataset.write(folder)
    return folder


def test_sizes_tell_how_large_the_instances_of_each_folder_are_and_where(tmp_path):
    near = write_squares(tmp_path / "near", [10, 20, 30, 40, 50], top=40)
    far = write_squares(tmp_path / "far", [4, 6, 8], top=90)
    assert sizes({"near": near, "far": far}).splitlines()[2:] == [
        "| near | 5 | 20 / 30 / 40 | 0.55 |", "| far | 3 | 5 / 6 / 7 | 0.93 |"]
