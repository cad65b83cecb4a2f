"""The end of a run (stages/app/summary.py): a short table per stage, the eval results, what was left out, the
warnings of cached stages, where the summary and previews are; the full table stays in summary.json."""
from __future__ import annotations

import json

from stages.app.summary import SHOWN, plan_report, run_report, summarise
from stages.engine.cache_entry import MANIFEST, Outcome
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
    outcomes = [Outcome("bg_depth", f"bg{k:03d}", "k", "cached", path=write_node(tmp_path / f"d{k}", {}),
                      warnings=["median depth implausible"] if k < 12 else []) for k in range(100)]
    outcomes += [Outcome("frames", "broken", "k", "failed", error="frames: cannot open video broken.mp4"),
                *(Outcome("splat_train", name, "k", "ran", seconds=60.0, started=1000.0 + delay,  # side by side
                         path=write_node(tmp_path / name, {})) for name, delay in (("mug", 0.0), ("can", 10.0))),
                Outcome("compose", "full", "k", "ran", seconds=30.0, started=1070.0,
                       left_out={"object broken": "frames[broken] failed"},
                       path=write_node(tmp_path / "compose", {"preview.png": b"png"})),
                Outcome("train_maskrcnn", "full", "k", "ran", seconds=200.0, started=1100.0,
                       path=write_node(tmp_path / "train", {})),
                Outcome("eval", "full@test", "k", "ran", seconds=5.0, started=1300.0,
                       path=write_node(tmp_path / "eval", {"metrics.json": metrics, "predictions.png": b"png"}))]
    summary = summarise(outcomes, compose_cfg([]), {}, [])
    assert len(summary["outcomes"]) == 106 and summary["compute_seconds_by_stage"]["bg_depth"] == 200.0
    lines = run_report(summary, outcomes, tmp_path / "summary.json").splitlines()
    assert len(lines) < 45
    assert lines[0].split() == ["stage", "items", "ran", "cached", "empty", "failed", "blocked", "work", "s", "wall",
                                "s"]
    assert lines[1].split() == ["bg_depth", "100", "0", "100", "0", "0", "0", "0.0", "0.0"]
    assert lines[3].split() == ["splat_train", "2", "2", "0", "0", "0", "0", "120.0", "70.0"]  # work, wall
    assert lines[4].split() == ["compose", "1", "1", "0", "0", "0", "0", "30.0", "30.0"]
    assert lines[7].split() == ["all", "106", "5", "100", "0", "1", "0", "355.0", "305.0"]
    assert "full@test: box AP 21.0 (AP50 49.0)  mask AP 19.5" in lines
    assert "  frames[broken]: frames: cannot open video broken.mp4" in lines
    assert "  compose[full] without object broken: frames[broken] failed" in lines
    assert "warnings (12):" in lines and f"  ... {12 - SHOWN} more in {tmp_path / 'summary.json'}" in lines
    assert f"  {tmp_path / 'compose' / 'preview.png'}" not in lines  # a shard's: the dataset stage shows the preview
    assert f"  {tmp_path / 'eval' / 'predictions.png'}" in lines
    assert lines[-1] == f"summary: {tmp_path / 'summary.json'}"


def test_the_plan_report_counts_and_names_the_problems(tmp_path):
    outcomes = [Outcome("frames", "mug", "k", "would-run"), Outcome("frames", "ghost", "?", "bad-input"),
               Outcome("compose", "full", "k", "would-run", left_out={"object ghost": "frames[ghost] bad-input"})]
    lines = plan_report(outcomes, {tmp_path / "ghost.mp4": "frames[ghost]: input ghost.mp4 not found"},
                        ["no test sets: eval skipped"], tmp_path / "plan.json").splitlines()
    assert lines[:3] == ["stage    items  cached  would-run  empty  bad-input  blocked",
                         "frames       2       0          1      0          1        0",
                         "compose      1       0          1      0          0        0"]
    assert lines[4:] == ["no test sets: eval skipped",
                         "input problems (1):", "  frames[ghost]: input ghost.mp4 not found",
                         "would run without (1):", "  compose[full] without object ghost: frames[ghost] bad-input",
                         f"plan: {tmp_path / 'plan.json'}"]


def test_photos_without_a_plane_are_counted_and_the_unexpected_named(tmp_path):
    metrics = {"photos": 40, "photos_without_plane": {"bg0000": "no planes found", "bg0006": "no planes found",
                                                      "bg0012": "no planes found"},
               "expected_without_plane": ["bg0000", "bg0006"]}
    outcomes = [Outcome("compose", f"full#{shard:04d}", "k", "cached",
                      path=write_node(tmp_path / f"compose{shard}", {"metrics.json": metrics})) for shard in range(3)]
    outcomes.append(Outcome("dataset", "full", "k", "cached",
                          path=write_node(tmp_path / "dataset", {"preview.png": b"png", "card.md": b"# card"})))
    summary = summarise(outcomes, compose_cfg([]), {}, [])
    assert list(summary["photos_without_plane"]) == ["compose[full]"]  # one dataset of three shards: said once
    assert summary["photos_without_plane"]["compose[full]"]["expected"] == ["bg0000", "bg0006"]
    assert summary["previews"] == [str(tmp_path / "dataset" / name) for name in ("preview.png", "card.md")]
    assert ("compose[full]: 3 of 40 photos have no placement plane: 2 of the sample, views without a floor (expected); "
            "1 not: bg0012 (no planes found)") in run_report(summary, outcomes, tmp_path / "summary.json").splitlines()


def test_empty_frame_slots_are_one_line_of_information_never_a_failure(tmp_path):
    """Slots a video could not fill: counted as empty in the table, named once under a short line with why (the
    compose groups left out for them are not listed again), never under failed, in the run and in the plan."""
    why = "room.mp4 gives 18 frames for 20 slots (12 windows of 0.02 motion, 0 dark, 1 blurred, 1 near-duplicates dropped)"
    outcomes = [Outcome(stage, f"room#{k}", "k", "empty", error=why)
               for stage in ("bg_depth", "planes") for k in (18, 19)]
    outcomes += [Outcome("bg_depth", "kitchen", "k", "cached", path=write_node(tmp_path / "kitchen", {})),
                Outcome("compose", "full", "k", "ran", seconds=3.0, started=1.0, path=write_node(tmp_path / "c", {}),
                       left_out={"photo room#18": f"bg_depth[room#18] empty: {why}",
                                 "photo torn": "bg_depth[torn] failed"})]
    summary = summarise(outcomes, compose_cfg([]), {}, [])
    assert summary["failed"] == [] and len(summary["empty"]) == 4
    lines = run_report(summary, outcomes, tmp_path / "summary.json").splitlines()
    assert lines[1].split()[:7] == ["bg_depth", "3", "0", "1", "2", "0", "0"]
    assert lines[lines.index("empty, nothing to compute (1):") + 1] == f"  room#18, room#19: {why}"
    assert "  compose[full] without photo torn: bg_depth[torn] failed" in lines
    assert not any("without photo room#18" in line for line in lines) and "failed (" not in "\n".join(lines)
    plan = plan_report(outcomes[:4], {}, [], tmp_path / "plan.json").splitlines()
    assert plan[1].split() == ["bg_depth", "2", "0", "0", "2", "0", "0"]
    assert plan[plan.index("empty, nothing to compute (1):") + 1] == f"  room#18, room#19: {why}"
