"""The replay benchmark's comparison (benchmarks/replay.py): which files and JSON keys differ."""
import json

from benchmarks.replay import compare, json_differences


def test_json_differences_name_the_leaves_that_differ():
    old = {"seconds": 1.5, "model": {"name": "a", "sizes": [1, 2]}, "kept": 3}
    new = {"seconds": 2.0, "model": {"name": "a", "sizes": [1, 5]}, "kept": 3, "extra": True}
    assert json_differences(old, new) == ["extra", "model.sizes[1]", "seconds"]
    assert json_differences(old, dict(old)) == []
    assert json_differences([1, 2], [1, 2, 3]) == ["(root)"]


def test_compare_counts_identical_files_and_narrows_json(tmp_path):
    replayed, entry = tmp_path / "replayed", tmp_path / "entry"
    for folder, seconds, pixel in ((replayed, 1.0, b"\x00"), (entry, 2.0, b"\x01")):
        (folder / "sub").mkdir(parents=True)
        (folder / "same.bin").write_bytes(b"abc")
        (folder / "sub" / "image.png").write_bytes(pixel)
        (folder / "stats.json").write_text(json.dumps({"seconds": seconds, "count": 4}))
        (folder / "metrics.json").write_text(json.dumps({"seconds": seconds}))  # the engine's: not compared
    (replayed / "only_here.txt").write_text("x")
    found = compare(replayed, entry)
    assert found["files"] == 3 and found["identical"] == 1
    assert found["differing"] == {"stats.json": ["seconds"], "sub/image.png": ["bytes"]}
    assert found["not_in_entry"] == ["only_here.txt"]
