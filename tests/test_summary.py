"""The end of a run (stages/summary.py): a short table per stage, the eval results, what was left out, the
warnings of cached stages, where the summary and previews are; the full table stays in summary.json."""
from __future__ import annotations

import json

from stages.engine import MANIFEST, Record
from stages.summary import SHOWN, plan_report, run_report, summarise
from tests.factories.configs import compose_cfg


def write_node(folder, files: dict[str, dict | bytes], seconds: float = 2.0):
    """A cache folder with a manifest (and `files`); returns its path as a string."""
    folder.mkdir(parents=True)
    (folder / MANIFEST).write_text(json.dumps({"seconds": seconds}))
    for name, content in files.items():
        (folder / name).write_bytes(content if isinstance(content, bytes) else json.dumps(content).encode())
    return str(folder)


def test_a_run_of_a_hundred_nodes_ends_with_a_short_report(tmp_path):
    metrics = {"bbox": {"AP": 21.04, "AP50": 49.0}, "segm": {"AP": 19.5}}
    records = [Record("bg_depth", f"bg{k:03d}", "k", "cached", path=write_node(tmp_path / f"d{k}", {}),
                      warnings=["median depth implausible"] if k < 12 else []) for k in range(100)]
    records += [Record("frames", "broken", "k", "failed", error="frames: cannot open video broken.mp4"),
                Record("compose", "full", "k", "ran", seconds=30.0, left_out={"object broken": "frames[broken] failed"},
                       path=write_node(tmp_path / "compose", {"preview.png": b"png"})),
                Record("train_maskrcnn", "full", "k", "ran", seconds=200.0, path=write_node(tmp_path / "train", {})),
                Record("eval", "full@test", "k", "ran", seconds=5.0,
                       path=write_node(tmp_path / "eval", {"metrics.json": metrics, "predictions.png": b"png"}))]
    summary = summarise(records, compose_cfg([]), {}, [])
    assert len(summary["records"]) == 104 and summary["compute_seconds_by_stage"]["bg_depth"] == 200.0
    lines = run_report(summary, records, tmp_path / "summary.json").splitlines()
    assert len(lines) < 45
    assert lines[0].split() == ["stage", "items", "ran", "cached", "failed", "blocked", "seconds"]
    assert lines[1].split() == ["bg_depth", "100", "0", "100", "0", "0", "0.0"]
    assert lines[3].split() == ["compose", "1", "1", "0", "0", "0", "30.0"]
    assert "full@test: box AP 21.0 (AP50 49.0)  mask AP 19.5" in lines
    assert "  frames[broken]: frames: cannot open video broken.mp4" in lines
    assert "  compose[full] without object broken: frames[broken] failed" in lines
    assert "warnings (12):" in lines and f"  ... {12 - SHOWN} more in {tmp_path / 'summary.json'}" in lines
    assert f"  {tmp_path / 'compose' / 'preview.png'}" in lines
    assert f"  {tmp_path / 'eval' / 'predictions.png'}" in lines
    assert lines[-1] == f"summary: {tmp_path / 'summary.json'}"


def test_the_plan_report_counts_and_names_the_problems(tmp_path):
    records = [Record("frames", "mug", "k", "would-run"), Record("frames", "ghost", "?", "bad-input"),
               Record("compose", "full", "k", "would-run", left_out={"object ghost": "frames[ghost] bad-input"})]
    lines = plan_report(records, {tmp_path / "ghost.mp4": "frames[ghost]: input ghost.mp4 not found"},
                        ["no test sets: eval skipped"], tmp_path / "plan.json").splitlines()
    assert lines[:3] == ["stage    items  cached  would-run  bad-input  blocked",
                         "frames       2       0          1          1        0",
                         "compose      1       0          1          0        0"]
    assert lines[4:] == ["no test sets: eval skipped",
                         "input problems (1):", "  frames[ghost]: input ghost.mp4 not found",
                         "would run without (1):", "  compose[full] without object ghost: frames[ghost] bad-input",
                         f"plan: {tmp_path / 'plan.json'}"]
