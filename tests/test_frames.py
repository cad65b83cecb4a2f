"""Tests of the frames stage on small videos and image folders written here with OpenCV."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from stages.contract.errors import StageError
from stages.engine.context import Context
from stages.frames import run as frames
from tests.factories.media import write_video


def make_ctx(inputs: dict, out: Path, **params) -> Context:
    out.mkdir(parents=True, exist_ok=True)
    return Context(stage="frames", item="test", params=params, inputs=inputs, out=out, seed=0)


def textured_frame(rng: np.random.Generator, shift: int, width: int = 160, height: int = 120) -> np.ndarray:
    """A BGR uint8 [H, W, 3] noise texture seen through a window that slides by `shift` pixels."""
    texture = cv2.resize(rng.integers(0, 255, (60, 120, 3), dtype=np.uint8), (width * 4, height),
                         interpolation=cv2.INTER_CUBIC)
    return np.ascontiguousarray(texture[:, shift:shift + width])


def moving_video(path: Path, count: int, blur_every: int = 0, step_px: int = 8) -> None:
    """`count` frames panning `step_px` per frame over one texture; frames whose index is not a
    multiple of `blur_every` are strongly blurred."""
    rng = np.random.default_rng(0)
    texture_rng_state = rng.bit_generator.state
    images = []
    for index in range(count):
        rng.bit_generator.state = texture_rng_state      # same texture in every frame
        image = textured_frame(rng, shift=index * step_px)
        if blur_every and index % blur_every:
            image = cv2.GaussianBlur(image, (0, 0), 3.0)
        images.append(image)
    write_video(path, images)


def photo_folder(folder: Path, shifts: list[int], blurred: tuple[int, ...] = ()) -> Path:
    """Photos img_00.png.. of one texture seen at the given shifts; those in `blurred` are blurred."""
    rng = np.random.default_rng(1)
    state = rng.bit_generator.state
    folder.mkdir()
    for index, shift in enumerate(shifts):
        rng.bit_generator.state = state
        image = textured_frame(rng, shift)
        cv2.imwrite(str(folder / f"img_{index:02d}.png"),
                    cv2.GaussianBlur(image, (0, 0), 3.0) if index in blurred else image)
    return folder


def test_video_keeps_sharpest_frame_per_motion_window(tmp_path):
    """A slow pan (2 px per frame, 1 % of the diagonal) in windows of 2 % motion: two frames per window,
    the sharp (even) one of each pair is kept, with time stamps and the source scale."""
    video = tmp_path / "pan.mp4"
    moving_video(video, 24, blur_every=2, step_px=2)
    metrics = frames.run(make_ctx({"video": video}, tmp_path / "out", motion_step=0.02, max_side=120))
    entries = json.loads((tmp_path / "out" / "frames.json").read_text())
    assert metrics["frames"] == len(entries) == metrics["windows"] == 12
    assert metrics["motion_total"] == pytest.approx(0.23, abs=0.02)
    assert all(e["source_index"] % 2 == 0 for e in entries)
    assert entries[3]["time_s"] == pytest.approx(entries[3]["source_index"] / 10)
    assert all(e["source"] == str(video) and e["scale"] == pytest.approx(0.75) for e in entries)
    image = cv2.imread(str(tmp_path / "out" / entries[0]["file"]))
    assert image.shape == (90, 120, 3)
    assert sorted(p.name for p in (tmp_path / "out" / "images").iterdir()) == [f"{i:04d}.jpg" for i in range(12)]


def test_fast_video_keeps_every_frame_and_max_frames_caps(tmp_path):
    """8 px per frame (4 % of the diagonal) is more than the default step: every frame is kept; max_frames=10
    widens the step so that 10 windows cover the pan."""
    video = tmp_path / "pan.mp4"
    moving_video(video, 20)
    assert frames.run(make_ctx({"video": video}, tmp_path / "all"))["frames"] == 20
    capped = frames.run(make_ctx({"video": video}, tmp_path / "capped", max_frames=10))
    assert capped["frames"] == 10 and capped["motion_step"] > 0.015


def test_image_folder_keeps_usable_photos_and_counts_the_rest(tmp_path):
    """Pairs of identical photos (duplicates), one blurred photo and an unreadable file among 12 photos."""
    folder = photo_folder(tmp_path / "photos", [(index // 2) * 20 for index in range(12)], blurred=(6,))
    (folder / "img_99.jpg").write_bytes(b"not a jpeg")
    metrics = frames.run(make_ctx({"video": folder}, tmp_path / "out", min_frames=3))
    entries = json.loads((tmp_path / "out" / "frames.json").read_text())
    assert metrics["blurred"] == 1 and metrics["duplicates_dropped"] == 5
    assert [Path(e["source"]).name for e in entries] == [f"img_{i:02d}.png" for i in (0, 2, 4, 7, 8, 10)]
    assert all(e["time_s"] is None and e["scale"] == 1.0 for e in entries)


def test_image_folder_exclude(tmp_path):
    folder = photo_folder(tmp_path / "photos", [index * 20 for index in range(10)])
    metrics = frames.run(make_ctx({"video": folder}, tmp_path / "out", exclude=["img_03.png", "img_07.png"]))
    names = [Path(e["source"]).name for e in json.loads((tmp_path / "out" / "frames.json").read_text())]
    assert metrics["excluded"] == 2 and metrics["frames"] == 8
    assert "img_03.png" not in names and "img_07.png" not in names
    with pytest.raises(StageError, match=r"frames.exclude names \['img_42.png'\], which are not images in"):
        frames.run(make_ctx({"video": folder}, tmp_path / "typo", exclude=["img_42.png"]))


def test_missing_input(tmp_path):
    with pytest.raises(StageError, match="nothing.mp4 does not exist"):
        frames.run(make_ctx({"video": tmp_path / "nothing.mp4"}, tmp_path / "out"))


def test_corrupt_video(tmp_path):
    video = tmp_path / "broken.mp4"
    video.write_bytes(np.random.default_rng(0).integers(0, 255, 5000, dtype=np.uint8).tobytes())
    with pytest.raises(StageError, match="broken.mp4"):
        frames.run(make_ctx({"video": video}, tmp_path / "out"))


def test_empty_video_file(tmp_path):
    video = tmp_path / "empty.mov"
    video.write_bytes(b"")
    with pytest.raises(StageError, match="empty.mov"):
        frames.run(make_ctx({"video": video}, tmp_path / "out"))


def test_empty_folder(tmp_path):
    (tmp_path / "shots").mkdir()
    with pytest.raises(StageError, match="shots contains no images"):
        frames.run(make_ctx({"video": tmp_path / "shots"}, tmp_path / "out"))


def test_too_few_frames(tmp_path):
    video = tmp_path / "short.mp4"
    moving_video(video, 4)
    with pytest.raises(StageError, match=r"short.mp4 gives 4 usable frames, at least 8"):
        frames.run(make_ctx({"video": video}, tmp_path / "out"))


def test_all_dark_frames(tmp_path):
    video = tmp_path / "night.avi"
    rng = np.random.default_rng(0)
    write_video(video, [rng.integers(0, 8, (120, 160, 3), dtype=np.uint8) for _ in range(12)])
    with pytest.raises(StageError, match=r"night.avi gives 0 usable frames.*too dark"):
        frames.run(make_ctx({"video": video}, tmp_path / "out"))


def test_static_video_is_all_duplicates(tmp_path):
    video = tmp_path / "tripod.mp4"
    image = textured_frame(np.random.default_rng(0), 0)
    write_video(video, [image] * 12)
    with pytest.raises(StageError, match=r"tripod.mp4 gives 1 usable frames.*near-duplicates"):
        frames.run(make_ctx({"video": video}, tmp_path / "out"))
