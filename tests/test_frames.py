"""Tests of the frames stage on small videos and image folders written here with OpenCV."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from stages import frames
from stages.context import Context, StageError
from tests.factories.media import write_video


def make_ctx(inputs: dict, out: Path, **params) -> Context:
    out.mkdir(parents=True, exist_ok=True)
    return Context(stage="frames", item="test", params=params, inputs=inputs, out=out, seed=0)


def textured_frame(rng: np.random.Generator, shift: int, width: int = 160, height: int = 120) -> np.ndarray:
    """A BGR uint8 [H, W, 3] noise texture seen through a window that slides by `shift` pixels."""
    texture = cv2.resize(rng.integers(0, 255, (60, 120, 3), dtype=np.uint8), (width * 4, height),
                         interpolation=cv2.INTER_CUBIC)
    return np.ascontiguousarray(texture[:, shift:shift + width])


def moving_video(path: Path, count: int, blur_every: int = 0) -> None:
    """`count` frames panning over one texture; every `blur_every`-th frame is strongly blurred."""
    rng = np.random.default_rng(0)
    texture_rng_state = rng.bit_generator.state
    images = []
    for index in range(count):
        rng.bit_generator.state = texture_rng_state      # same texture in every frame
        image = textured_frame(rng, shift=index * 8)
        if blur_every and index % blur_every:
            image = cv2.GaussianBlur(image, (0, 0), 3.0)
        images.append(image)
    write_video(path, images)


def test_video_keeps_sharpest_frame_per_window(tmp_path):
    """20 frames in 10 windows of 2: the sharp (even) frame of each pair is kept, with time stamps."""
    video = tmp_path / "pan.mp4"
    moving_video(video, 20, blur_every=2)
    metrics = frames.run(make_ctx({"video": video}, tmp_path / "out", num_frames=10, max_side=80))
    entries = json.loads((tmp_path / "out" / "frames.json").read_text())
    assert metrics["frames"] == len(entries) == 10
    assert [e["source_index"] for e in entries] == list(range(0, 20, 2))
    assert entries[3]["time_s"] == pytest.approx(0.6)
    assert all(e["source"] == str(video) and e["scale"] == pytest.approx(0.5) for e in entries)
    image = cv2.imread(str(tmp_path / "out" / entries[0]["file"]))
    assert image.shape == (60, 80, 3)
    assert sorted(p.name for p in (tmp_path / "out" / "images").iterdir()) == [f"{i:04d}.jpg" for i in range(10)]


def test_image_folder_drops_duplicates_and_skips_unreadable(tmp_path):
    rng = np.random.default_rng(1)
    folder = tmp_path / "photos"
    folder.mkdir()
    state = rng.bit_generator.state
    for index in range(10):
        rng.bit_generator.state = state
        shift = (index // 2) * 20                         # pairs of identical photos
        cv2.imwrite(str(folder / f"img_{index:02d}.png"), textured_frame(rng, shift))
    (folder / "img_99.jpg").write_bytes(b"not a jpeg")
    metrics = frames.run(make_ctx({"video": folder}, tmp_path / "out", num_frames=20, min_frames=3))
    entries = json.loads((tmp_path / "out" / "frames.json").read_text())
    assert metrics["duplicates_dropped"] == 5
    assert [Path(e["source"]).name for e in entries] == [f"img_{i:02d}.png" for i in range(0, 10, 2)]
    assert all(e["time_s"] is None and e["scale"] == 1.0 for e in entries)


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
