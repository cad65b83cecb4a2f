"""Bounded readers (issue 58, stages/lib/file_checks.py): declared sizes are checked against the file before anything
is allocated, NaNs are refused where none can be meant and kept in depth (no depth), and images, depth maps and
video frames above `run.max_image_pixels` are refused with a message naming the file and the setting. The fuzz
tests (tests/test_fuzz_readers.py) try every reader with thousands of bad files; these pin single behaviours."""
from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from stages.contract.errors import StageError
from stages.lib.capture.video_frames import open_video
from stages.lib.depth.formats import read_sidecar_depth
from stages.lib.file_checks import MAX_PIXELS_ENV, check_pixels, count_text, load_json, load_npy, require_finite
from stages.lib.gaussians.ply import read_gaussians
from stages.lib.imageio import load_photo
from stages.lib.torch_files import load_torch_file
from tests.factories import fuzz_seeds as seeds


@pytest.fixture
def small_limit(monkeypatch):
    """The pixel limit set to 1000 pixels, as `run.max_image_pixels=1000` sets it for dag.py and its workers."""
    monkeypatch.setenv(MAX_PIXELS_ENV, "1000")


def test_the_pixel_limit_is_configurable_and_named(tmp_path, small_limit):
    (tmp_path / "photo.png").write_bytes(seeds.photo_png())
    (tmp_path / "photo.depth.png").write_bytes(seeds.depth_png())
    (tmp_path / "video.mp4").write_bytes(seeds.video_bytes(tmp_path))
    message = "64x48 is 0.0 megapixels, above the limit of 0.001 megapixels; downscale it, or raise run.max_image_pixels"
    for read, name in ((load_photo, "photo.png"), (lambda p: read_sidecar_depth(p, "png_mm"), "photo.depth.png"),
                       (open_video, "video.mp4")):
        with pytest.raises(StageError, match=f"{tmp_path / name}: {message}"):
            read(tmp_path / name)


def test_the_default_limit_reads_the_seeds_and_refuses_a_lying_size(tmp_path):
    (tmp_path / "photo.png").write_bytes(seeds.png_size(seeds.photo_png(), 40000, 40000))
    with pytest.raises(StageError, match="40000x40000 is 1600.0 megapixels, above the limit of 50 megapixels"):
        load_photo(tmp_path / "photo.png")
    with pytest.raises(StageError, match=r"about 10\^400x1 is about 10\^394 megapixels"):
        check_pixels(tmp_path / "x", "image", 10 ** 400, 1)
    assert count_text(123) == "123"


def test_a_lying_ply_header_is_refused_before_anything_is_allocated(tmp_path):
    """The PLY of issue 58: its header says 10^10 vertices, it holds 10."""
    data = seeds.ply_bytes().replace(b"element vertex 20\n", b"element vertex 10000000000\n")
    (tmp_path / "plant.ply").write_bytes(data[:data.index(b"end_header\n") + 11 + 10 * 104])
    with pytest.raises(StageError, match=f"Gaussian PLY {tmp_path / 'plant.ply'}: its header declares 10000000000 "
                                         r"vertices of 104 bytes \(1040000000000 bytes\), but the file holds 1040"):
        read_gaussians(tmp_path / "plant.ply")


def test_nan_is_refused_in_a_model_and_kept_as_no_depth_in_a_depth_map(tmp_path):
    (tmp_path / "nan.ply").write_bytes(seeds.ply_with_value("x", math.nan))
    with pytest.raises(StageError, match="nan.ply: its positions hold 1 NaN or infinite values"):
        read_gaussians(tmp_path / "nan.ply")
    depth = seeds.depth_npy()
    depth[:10] = np.nan
    np.save(tmp_path / "photo.depth.npy", depth)
    read = read_sidecar_depth(tmp_path / "photo.depth.npy", "npy_m")
    assert (read[:10] == 0).all() and (read[10:] > 0).all()
    with pytest.raises(StageError, match="x: its K hold 2 NaN or infinite values"):
        require_finite(tmp_path / "x", "camera", K=[[math.nan, math.inf]])


def test_an_npy_header_that_declares_more_than_the_file_holds(tmp_path):
    lie = {"descr": "<f4", "fortran_order": False, "shape": (100000, 100000)}
    (tmp_path / "a.npy").write_bytes(seeds.npy_bytes(seeds.depth_npy(), lie))
    with pytest.raises(StageError, match=r"array of shape \(100000, 100000\) \(40000000000 bytes\), but the file holds "
                                         "12288 bytes"):
        load_npy(tmp_path / "a.npy", "depth map")


def test_json_nested_too_deep_is_a_named_error(tmp_path):
    (tmp_path / "a.json").write_bytes(b"[" * 100_000 + b"]" * 100_000)
    with pytest.raises(StageError, match="a.json: not valid JSON \\(RecursionError"):
        load_json(tmp_path / "a.json", "intrinsics file")


def test_a_truncated_torch_file_is_named_and_a_truncated_checkpoint_is_ignored(tmp_path, caplog):
    from stages.train_maskrcnn.run import load_checkpoint
    from stages.train_maskrcnn.spec import TrainMaskrcnnConfig

    data = seeds.torch_file()
    (tmp_path / "last.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(StageError, match="last.pt: not a file written by torch.save"):
        load_torch_file(tmp_path / "last.pt", "checkpoint")
    with caplog.at_level(logging.WARNING):
        assert load_checkpoint(tmp_path / "last.pt", TrainMaskrcnnConfig(), 0) is None
    assert "training starts over" in caplog.text
