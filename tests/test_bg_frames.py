"""A background video's frame slots (stages/bg_frames/run.py): frames chosen as a capture's are, written into slots
sized before anything runs; a slot the video cannot fill is empty, not failed, and the other backgrounds go on."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from stages.app.pipeline import build_graph
from stages.app.preflight import check_inputs
from stages.app.summary import data_line
from stages.bg_depth import run as bg_depth
from stages.bg_frames import run as bg_frames
from stages.contract.errors import EmptyInput
from stages.engine.context import Context
from stages.engine.scheduler import Engine
from stages.lib.imageio import load_photo
from stages.records.bg_frames import BgFramesRecord
from tests.factories.configs import compose_cfg
from tests.factories.media import noise_video, read_video_frames, write_image, write_video

WIDTH, HEIGHT = 96, 72


def run_stage(module, item: str, inputs: dict, out: Path, **params) -> dict:
    """Run a stage module on `inputs` into a new folder `out`; its metrics."""
    out.mkdir(parents=True)
    return module.run(Context(module.__name__.rpartition(".")[2], item, params, inputs, out))


def still_video(path: Path, count: int) -> Path:
    """`count` frames of one textured image: a camera that does not move."""
    image = np.random.default_rng(5).integers(30, 225, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    return write_video(path, [image] * count)


def test_a_video_fills_its_slots_with_frames_spread_over_it(tmp_path):
    video = noise_video(tmp_path / "room.mp4", 30, WIDTH, HEIGHT)
    metrics = run_stage(bg_frames, "room", {"video": video}, tmp_path / "out", count=5)
    record = BgFramesRecord.read(tmp_path / "out")
    indices = [slot.source_index for slot in record.slots]
    assert metrics["slots"] == metrics["filled"] == 5 and not any(slot.empty for slot in record.slots)
    assert indices == sorted(indices) and indices[0] <= 6 and indices[-1] >= 23  # spread over the video
    assert [slot.time_s for slot in record.slots] == [pytest.approx(i / 10.0) for i in indices]
    decoded = read_video_frames(video)
    for k, index in enumerate(indices):  # each slot holds its frame at the video's own size
        written = load_photo(tmp_path / "out" / BgFramesRecord.image(k))[..., ::-1]
        assert np.array_equal(written, decoded[index])


def test_a_camera_that_hardly_moves_fills_fewer_slots_and_the_others_are_empty(tmp_path):
    video = still_video(tmp_path / "still.mp4", 12)
    metrics = run_stage(bg_frames, "still", {"video": video}, tmp_path / "out", count=5)
    record = BgFramesRecord.read(tmp_path / "out")
    assert (metrics["slots"], metrics["filled"]) == (5, 1) and record.slots[0].source_index is not None
    assert [slot.empty for slot in record.slots[1:]] == [record.slots[1].empty] * 4
    assert record.slots[1].empty.startswith("still.mp4 gives 1 frames for 5 slots (1 windows of")
    params = {"provider": "auto", "model": "none"}
    image = tmp_path / "out" / BgFramesRecord.image(3)
    assert BgFramesRecord.empty_reason(image) == record.slots[3].empty
    with pytest.raises(EmptyInput, match="still.mp4 gives 1 frames for 5 slots"):
        run_stage(bg_depth, "still#3", {"image": image}, tmp_path / "depth3", **params)
    filled = run_stage(bg_depth, "still#0", {"image": tmp_path / "out" / BgFramesRecord.image(0)},
                       tmp_path / "depth0", **params)
    assert filled["provider"] == "none"
    assert BgFramesRecord.empty_reason(tmp_path / "out" / BgFramesRecord.image(0)) is None


def user_backgrounds(root: Path, backgrounds: str) -> tuple:
    """The graph of a user's data (one object, never run here) with data.backgrounds=`backgrounds` under `root`,
    which holds photos/ (two photos), videos/still.mp4 (12 still frames) and videos/pan.mp4 (30 distinct frames)."""
    (root / "videos").mkdir(parents=True)
    noise_video(root / "videos" / "pan.mp4", 30, WIDTH, HEIGHT)
    still_video(root / "videos" / "still.mp4", 12)
    (root / "photos").mkdir()
    for k, name in enumerate(("kitchen", "hall")):
        write_image(root / "photos" / f"{name}.png", np.random.default_rng(k).integers(0, 255, (HEIGHT, WIDTH, 3),
                                                                                       dtype=np.uint8))
    cfg = compose_cfg(["data=folder", "data.objects=[{name: mug, height_m: 0.1, video: videos/pan.mp4}]",
                       f"data.backgrounds={backgrounds}", "data.test_sets=[]", "bg_depth.model=none",
                       "bg_frames.count=5"])
    return cfg, build_graph(cfg, root)


def test_videos_among_the_backgrounds_become_photo_nodes_and_empty_slots_leave_the_rest_going(tmp_path):
    """Slots are sized from the headers before anything runs; a run fills them; the still video's empty slots are
    empty (bg_depth and planes) and cached so, the photos and the other video's frames go on."""
    cfg, graph = user_backgrounds(tmp_path, "[photos,videos/still.mp4,videos/pan.mp4]")
    photos = [n.item for n in graph.nodes["bg_depth"]]
    assert photos == ["hall", "kitchen"] + [f"still#{k}" for k in range(5)] + [f"pan#{k}" for k in range(5)]
    assert [n.item for n in graph.nodes["bg_frames"]] == ["still", "pan"]
    assert data_line(graph.nodes).split("; ")[1] == (f"12 background photos: 5 frames of {tmp_path}/videos/still.mp4, "
                                                     f"5 frames of {tmp_path}/videos/pan.mp4, 2 from {tmp_path}/photos")
    assert check_inputs(graph, ["mug"]) == {}
    targets = graph.targets("planes")
    records = Engine(tmp_path / "cache").run(targets)
    status = {r.label: r.status for r in records}
    assert [status[f"planes[still#{k}]"] for k in range(5)] == ["ran"] + ["empty"] * 4
    assert [status[f"bg_depth[still#{k}]"] for k in range(5)] == ["ran"] + ["empty"] * 4
    assert all(status[f"planes[{p}]"] == "ran" for p in ("kitchen", "hall", *(f"pan#{k}" for k in range(5))))
    plan = Engine(tmp_path / "cache").plan(targets)
    assert {r.label: r.status for r in plan} == {**status, **{label: "cached" for label, s in status.items()
                                                              if s == "ran"}}


def test_a_video_that_cannot_be_read_gets_no_slot_and_is_named_before_anything_runs(tmp_path):
    (tmp_path / "videos").mkdir()
    (tmp_path / "videos" / "broken.mp4").write_bytes(np.random.default_rng(0).bytes(4096))
    cfg, graph = user_backgrounds(tmp_path / "data", f"[photos,{tmp_path}/videos/broken.mp4,{tmp_path}/ghost.mp4]")
    assert [n.item for n in graph.nodes["bg_depth"]] == ["hall", "kitchen"]
    problems = check_inputs(graph, ["mug"])
    assert list(problems) == [tmp_path / "videos" / "broken.mp4", tmp_path / "ghost.mp4"]
    assert "bg_frames: cannot open video" in problems[tmp_path / "videos" / "broken.mp4"]
    assert "input " + str(tmp_path / "ghost.mp4") + " not found" in problems[tmp_path / "ghost.mp4"]
    plan = {r.label: r.status for r in Engine(tmp_path / "cache").plan(graph.targets(None), problems)}
    assert plan["bg_frames[broken]"] == plan["bg_frames[ghost]"] == "bad-input"
    assert plan["compose[full#0]"] == "would-run"


def test_the_stage_writes_what_its_record_says(tmp_path):
    video = noise_video(tmp_path / "room.mp4", 8, WIDTH, HEIGHT)
    run_stage(bg_frames, "room", {"video": video}, tmp_path / "out", count=20)
    data = json.loads((tmp_path / "out" / BgFramesRecord.JSON).read_text())
    assert data["video"] == str(video) and len(data["slots"]) == 8  # min(count, the 8 frames its header states)
    assert sorted(p.name for p in (tmp_path / "out" / "images").iterdir()) == [
        Path(BgFramesRecord.image(k)).name for k in range(sum(s["empty"] == "" for s in data["slots"]))]
