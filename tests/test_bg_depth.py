"""Tests for stages/bg_depth/run.py, stages/lib/depth/formats.py and stages/lib/depth/onnx.py (the transformers models
and the recovery of relative depth: tests/test_depth_models.py, tests/test_depth_recovery.py)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper
from PIL import Image

from stages.bg_depth import run as bg_depth
from stages.contract.errors import StageError
from stages.engine.context import Context
from stages.lib.depth import formats as depth_formats
from stages.lib.depth import intrinsics
from stages.lib.depth import onnx as depth_onnx
from tests.factories.media import write_image



def true_depth(height: int = 48, width: int = 64) -> np.ndarray:
    """A depth ramp 0.8..4.0 m with a missing corner: float32 [H, W]."""
    depth = np.linspace(0.8, 4.0, width, dtype=np.float32)[None].repeat(height, axis=0)
    depth[:4, :4] = 0
    return depth


# ---------------------------------------------------------------- sidecar formats

def test_png_mm_and_auto_detection(tmp_path):
    depth = true_depth()
    path = tmp_path / "room.depth.png"
    cv2.imwrite(str(path), np.rint(depth * 1000).astype(np.uint16))
    assert depth_formats.detect_sidecar_format(path) == "png_mm"
    np.testing.assert_allclose(depth_formats.read_sidecar_depth(path), depth, atol=5e-4)


def test_npy_metres(tmp_path):
    depth = true_depth()
    depth[5, 5] = np.nan
    np.save(tmp_path / "d.npy", depth[..., None])
    decoded = depth_formats.read_sidecar_depth(tmp_path / "d.npy")
    assert decoded[5, 5] == 0 and decoded.shape == depth.shape
    np.testing.assert_allclose(decoded[10:], depth[10:])


def test_tum_encoding(tmp_path):
    depth = true_depth()
    path = tmp_path / "scene_tum.png"
    cv2.imwrite(str(path), np.rint(depth * 5000).astype(np.uint16))
    assert depth_formats.detect_sidecar_format(path) == "tum"
    np.testing.assert_allclose(depth_formats.read_sidecar_depth(path), depth, atol=2e-4)


def test_sun_bit_rotation(tmp_path):
    depth = true_depth()
    millimetres = np.rint(depth * 1000).astype(np.uint32)
    rotated = (((millimetres << 3) | (millimetres >> 13)) & 0xFFFF).astype(np.uint16)
    path = tmp_path / "x.png"
    cv2.imwrite(str(path), rotated)
    np.testing.assert_allclose(depth_formats.read_sidecar_depth(path, "sun"), depth, atol=5e-4)
    assert not np.allclose(depth_formats.read_sidecar_depth(path, "png_mm"), depth, atol=0.1)


@pytest.mark.parametrize("byte_order", [">u2", "<u2"])
def test_nyu_raw_disparity_either_byte_order(tmp_path, byte_order):
    depth = true_depth()
    raw = np.where(depth > 0, np.rint(1092.5 - 351.3 / np.maximum(depth, 1e-3)), 2047).astype(np.uint16)
    path = tmp_path / "scene.pgm"
    path.write_bytes(b"P5\n64 48\n65535\n" + raw.astype(byte_order).tobytes())
    decoded = depth_formats.read_sidecar_depth(path)
    expected = np.where(depth > 0, 351.3 / (1092.5 - raw.astype(np.float32)), 0)
    np.testing.assert_allclose(decoded, expected, rtol=1e-5)
    np.testing.assert_allclose(decoded[depth > 0], depth[depth > 0], rtol=0.02)   # quantised
    assert (decoded[:4, :4] == 0).all()


@pytest.mark.parametrize("color, depth_file, fmt, median_range", [
    ("TUM_color.png", "TUM_depth.png", "tum", (1.5, 4.0)),
    ("NYU_color.ppm", "NYU_depth.pgm", "nyu", (1.5, 6.0)),
    ("SUN_color.jpg", "SUN_depth.png", "sun", (1.5, 5.0)),
])
def test_real_rgbd_sidecars(tmp_path, color, depth_file, fmt, median_range, real):
    rgbd = real / "rgbd"
    assert depth_formats.detect_sidecar_format(rgbd / depth_file) == fmt
    metrics = bg_depth.run(Context("bg_depth", fmt, {}, {"image": rgbd / color, "depth": rgbd / depth_file},
                                   tmp_path))
    depth = np.load(tmp_path / "depth.npy")
    record = json.loads((tmp_path / "depth.json").read_text())
    assert depth.shape == (480, 640) and depth.dtype == np.float32
    assert record["provider"] == "sidecar" and record["metric"] is True
    assert metrics["valid_fraction"] > 0.75
    valid = depth[depth > 0]
    assert median_range[0] < np.median(valid) < median_range[1]
    assert valid.min() > 0.2 and valid.max() < 12.0


@pytest.mark.parametrize("case", ["all_zero", "rgb_png", "garbage", "bad_extension"])
def test_bad_sidecar_is_a_clear_error(tmp_path, case):
    path = {"all_zero": tmp_path / "z.png", "rgb_png": tmp_path / "c.png", "garbage": tmp_path / "g.png",
            "bad_extension": tmp_path / "d.tiff"}[case]
    if case == "all_zero":
        cv2.imwrite(str(path), np.zeros((40, 40), np.uint16))
    elif case == "rgb_png":
        cv2.imwrite(str(path), np.full((40, 40, 3), 9, np.uint8))
    else:
        path.write_bytes(b"\x00garbage")
    with pytest.raises(StageError, match=path.name):
        depth_formats.read_sidecar_depth(path)


def test_sidecar_file_name_rule(tmp_path):
    """<stem>.depth.<format>.<ext> names the encoding; the photo's own name does not (sun_room is no SUN file)."""
    photo = write_image(tmp_path / "sun_room.png", np.full((48, 64, 3), 50, np.uint8))
    tum = tmp_path / "sun_room.depth.tum.png"
    cv2.imwrite(str(tum), np.rint(true_depth() * 5000).astype(np.uint16))
    assert depth_formats.find_sidecar_files(photo)["depth"] == tum and depth_formats.is_depth_sidecar(tum)
    assert depth_formats.detect_sidecar_format(tum) == "tum"
    np.testing.assert_allclose(depth_formats.read_sidecar_depth(tum), true_depth(), atol=2e-4)
    assert depth_formats.detect_sidecar_format(tmp_path / "sun_room.depth.png") == "png_mm"
    assert not depth_formats.is_depth_sidecar(photo)


def run_with_sidecar(tmp_path: Path, name: str, values: np.ndarray, params: dict | None = None) -> dict:
    """bg_depth on a 64x48 photo `room.png` with the uint16 `values` [48, 64] saved as sidecar `name`."""
    image = write_image(tmp_path / "room.png", np.full((48, 64, 3), 50, np.uint8))
    cv2.imwrite(str(tmp_path / name), values)
    out = tmp_path / f"out_{name}"
    out.mkdir()
    inputs = {"image": image, "depth": tmp_path / name}
    return bg_depth.run(Context("bg_depth", "room", dict(params or {}), inputs, out))


def test_tum_depth_under_a_plain_name_is_flagged_with_the_encoding_that_fits(tmp_path, caplog):
    tum_values = np.rint(true_depth() * 5000).astype(np.uint16)                  # median 2.43 m
    metrics = run_with_sidecar(tmp_path, "room.depth.png", tum_values)
    assert metrics["sidecar_format"] == "png_mm" and metrics["median_depth"] == pytest.approx(12.13, abs=0.01)
    assert (f"depth sidecar {tmp_path / 'room.depth.png'}: median depth 12.13 m when read as png_mm is implausible "
            "for a photo to place objects in (expected 0.3 to 8 m); as tum it is 2.43 m: set "
            "bg_depth.sidecar_format=tum or name the file room.depth.tum.png") in caplog.text
    caplog.clear()
    for name, params in (("room.depth.tum.png", {}), ("plain.depth.png", {"sidecar_format": "tum"})):
        metrics = run_with_sidecar(tmp_path, name, tum_values, params)
        assert metrics["sidecar_format"] == "tum" and metrics["median_depth"] == pytest.approx(2.43, abs=0.01)
    assert "implausible" not in caplog.text


def test_sun_depth_read_as_tum_is_flagged_by_its_bit_rotation(tmp_path, caplog):
    millimetres = np.rint(true_depth() * 1000).astype(np.uint32)
    rotated = (((millimetres << 3) | (millimetres >> 13)) & 0xFFFF).astype(np.uint16)
    run_with_sidecar(tmp_path, "room.depth.png", rotated, {"sidecar_format": "tum"})  # median 3.88 m: plausible
    assert "bear the bit rotation of SUN RGB-D depth (multiples of 8); as sun it is 2.42 m" in caplog.text


def test_real_tum_depth_under_a_plain_name_is_flagged(tmp_path, caplog, real):
    rgbd = real / "rgbd"
    metrics = bg_depth.run(Context("bg_depth", "office", {}, {"image": rgbd / "TUM_color.png",
                                                               "depth": rgbd / "TUM_depth.png"}, tmp_path))
    assert metrics["sidecar_format"] == "tum" and "implausible" not in caplog.text  # its name says TUM
    (tmp_path / "office.depth.png").write_bytes((rgbd / "TUM_depth.png").read_bytes())
    out = tmp_path / "plain"
    out.mkdir()
    metrics = bg_depth.run(Context("bg_depth", "office", {}, {"image": rgbd / "TUM_color.png",
                                                               "depth": tmp_path / "office.depth.png"}, out))
    assert metrics["median_depth"] == pytest.approx(12.07, abs=0.01)
    assert "as tum it is 2.41 m: set bg_depth.sidecar_format=tum or name the file office.depth.tum.png" in caplog.text


# ---------------------------------------------------------------- intrinsics

def test_intrinsics_sources(tmp_path):
    K, source = intrinsics.resolve_intrinsics(tmp_path / "none.png", 640, 480)
    assert source == "fov" and K[0, 0] == pytest.approx(320 / math.tan(math.radians(27.5)))
    assert K[0, 2] == 320 and K[1, 2] == 240
    exif = Image.Exif()
    exif.get_ifd(intrinsics.EXIF_IFD)[intrinsics.EXIF_FOCAL_35MM] = 26
    jpeg = tmp_path / "phone.jpg"
    Image.fromarray(np.zeros((300, 400, 3), np.uint8)).save(jpeg, exif=exif)
    K, source = intrinsics.resolve_intrinsics(jpeg, 400, 300)
    assert source == "exif" and K[0, 0] == pytest.approx(26 * 500 / math.hypot(36, 24))
    sidecar = tmp_path / "phone.json"
    sidecar.write_text(json.dumps({"K": [[300, 0, 200], [0, 300, 150], [0, 0, 1]]}))
    K, source = intrinsics.resolve_intrinsics(jpeg, 400, 300, intrinsics_json=sidecar)
    assert source == "json" and K[0, 0] == 300
    K, source = intrinsics.resolve_intrinsics(jpeg, 400, 300, config_K=[[100, 0, 1], [0, 100, 1], [0, 0, 1]])
    assert source == "config" and K[0, 0] == 100
    with pytest.raises(StageError, match="3x3"):
        intrinsics.resolve_intrinsics(jpeg, 400, 300, config_K=[[1, 2], [3, 4]])


# ---------------------------------------------------------------- run: providers

def test_sidecar_run_uses_files_beside_the_photo(tmp_path):
    depth = true_depth()
    image = write_image(tmp_path / "bg01.png", np.full((48, 64, 3), 50, np.uint8))
    cv2.imwrite(str(tmp_path / "bg01.depth.png"), np.rint(depth * 1000).astype(np.uint16))
    (tmp_path / "bg01.json").write_text(json.dumps({"K": [[60, 0, 32], [0, 60, 24], [0, 0, 1]]}))
    out = tmp_path / "out"
    out.mkdir()
    metrics = bg_depth.run(Context("bg_depth", "bg01", {}, {"image": image}, out))
    record = json.loads((out / "depth.json").read_text())
    assert record == {"provider": "sidecar", "metric": True, "K": [[60, 0, 32], [0, 60, 24], [0, 0, 1]],
                      "width": 64, "height": 48, "sidecar_format": "png_mm", "model": None, "recovery": None}
    assert metrics["K_source"] == "json"
    np.testing.assert_allclose(np.load(out / "depth.npy"), depth, atol=5e-4)


def test_no_depth_available_writes_provider_none(tmp_path, caplog):
    image = write_image(tmp_path / "photo.png", np.full((48, 64, 3), 50, np.uint8))
    out = tmp_path / "out"
    out.mkdir()
    metrics = bg_depth.run(Context("bg_depth", "p", {"model": "none"}, {"image": image}, out))
    assert metrics["provider"] == "none" and not (out / "depth.npy").exists()
    assert json.loads((out / "depth.json").read_text())["provider"] == "none"
    assert "no depth and no placement plane: compose's placement 'plane' leaves it out while another photo has " \
           "a plane (placement 'random' uses it)" in caplog.text
    with pytest.raises(StageError, match="sidecar"):
        bg_depth.run(Context("bg_depth", "p", {"provider": "sidecar"}, {"image": image}, out))
    with pytest.raises(StageError, match="provider 'model' needs bg_depth.model"):
        bg_depth.run(Context("bg_depth", "p", {"provider": "model", "model": "none"}, {"image": image}, out))


def test_sidecar_of_the_wrong_size(tmp_path):
    image = write_image(tmp_path / "photo.png", np.full((48, 64, 3), 50, np.uint8))
    np.save(tmp_path / "half.npy", true_depth(24, 32))
    with pytest.raises(StageError, match="half.npy.*does not match"):
        bg_depth.run(Context("bg_depth", "p", {}, {"image": image, "depth": tmp_path / "half.npy"}, tmp_path))


# ---------------------------------------------------------------- ONNX depth models

def gray_plus_offset_model(path: Path, height="H", width="W", offset: float = 0.1) -> None:
    """A 1x1 conv that undoes ImageNet normalisation: output [1, h, w] = mean RGB in [0, 1] + offset."""
    weight = (depth_onnx.IMAGENET_STD / 3.0).reshape(1, 3, 1, 1).astype(np.float32)
    bias = np.array([depth_onnx.IMAGENET_MEAN.sum() / 3.0 + offset], np.float32)
    graph = helper.make_graph(
        [helper.make_node("Conv", ["image", "w", "b"], ["conv"]),
         helper.make_node("Squeeze", ["conv", "axis"], ["depth"])],
        "gray_depth",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, height, width])],
        [helper.make_tensor_value_info("depth", TensorProto.FLOAT, [1, height, width])],
        [numpy_helper.from_array(weight, "w"), numpy_helper.from_array(bias, "b"),
         numpy_helper.from_array(np.array([1], np.int64), "axis")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def gradient_photo(tmp_path: Path) -> tuple[Path, np.ndarray]:
    """A 64x48 photo whose gray value ramps left to right; returns (path, gray in [0, 1] [H, W])."""
    ramp = np.linspace(40, 220, 64).round().astype(np.uint8)[None].repeat(48, axis=0)
    return write_image(tmp_path / "ramp.png", np.dstack([ramp] * 3)), ramp / 255.0


def test_onnx_metric_model_pre_and_post_processing(tmp_path):
    model = tmp_path / "metric.onnx"
    gray_plus_offset_model(model)
    image, gray = gradient_photo(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    params = {"provider": "model", "model": str(model), "model_output": "metric_depth", "model_input_size": 28}
    metrics = bg_depth.run(Context("bg_depth", "ramp", params, {"image": image}, out))
    depth = np.load(out / "depth.npy")
    assert metrics["metric"] is True and depth.shape == (48, 64) and metrics["model"] == str(model)
    assert json.loads((out / "depth.json").read_text())["model"] == {"name": str(model), "kind": "onnx",
                                                                    "path": str(model), "output": "metric_depth"}
    np.testing.assert_allclose(depth[:, 4:-4], gray[:, 4:-4] + 0.1, atol=0.01)


def test_onnx_relative_model_static_size(tmp_path):
    model = tmp_path / "relative.onnx"
    gray_plus_offset_model(model, 28, 42)
    image, gray = gradient_photo(tmp_path)
    session = depth_onnx.load_depth_session(model)
    assert depth_onnx.model_input_size(session, 48, 64, 518) == (28, 42)
    out = tmp_path / "out"
    out.mkdir()
    bg_depth.run(Context("bg_depth", "ramp", {"model": str(model)}, {"image": image}, out))
    record = json.loads((out / "depth.json").read_text())
    assert record["provider"] == "model" and record["metric"] is True and record["model"]["output"] == "disparity"
    recovery = record["recovery"]  # a ramp has no planar structure to tell the shift: 0, scale from the median
    assert recovery["shift"] == 0 and "do not tell it" in recovery["shift_from"]
    assert recovery["scale_from"].startswith("median depth")
    disparity = gray + 0.1
    expected = recovery["scale_m"] * np.median(disparity) / disparity        # depth = scale / (d / median - 0)
    np.testing.assert_allclose(np.load(out / "depth.npy")[:, 4:-4], expected[:, 4:-4], rtol=0.03)
    as_input = tmp_path / "as_input"  # the DAG passes the model as input "model" (keyed by content)
    as_input.mkdir()
    bg_depth.run(Context("bg_depth", "ramp", {"model": "local"}, {"image": image, "model": model}, as_input))
    np.testing.assert_array_equal(np.load(as_input / "depth.npy"), np.load(out / "depth.npy"))


def test_onnx_model_dynamic_size_follows_depth_anything_resize(tmp_path):
    model = tmp_path / "dyn.onnx"
    gray_plus_offset_model(model)
    session = depth_onnx.load_depth_session(model)
    assert depth_onnx.model_input_size(session, 480, 640, 518) == (518, 686)
    assert depth_onnx.model_input_size(session, 1080, 720, 518) == (784, 518)


def test_onnx_file_that_is_not_a_depth_model(tmp_path):
    graph = helper.make_graph(
        [helper.make_node("Identity", ["image"], ["same"])], "identity",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, "H", "W"])],
        [helper.make_tensor_value_info("same", TensorProto.FLOAT, [1, 3, "H", "W"])])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    path = tmp_path / "classifier.onnx"
    onnx.save(model, str(path))
    image, _ = gradient_photo(tmp_path)
    params = {"provider": "model", "model": str(path), "model_input_size": 28}
    with pytest.raises(StageError, match="classifier.onnx.*not a depth model"):
        bg_depth.run(Context("bg_depth", "x", params, {"image": image}, tmp_path))
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"definitely not protobuf")
    with pytest.raises(StageError, match="garbage.onnx"):
        depth_onnx.load_depth_session(garbage)


def test_rgbd_pairs_of_the_real_samples_are_found_with_their_encodings(real):
    """<name>_color.<ext> beside <name>_depth.<ext> (TUM, NYU, SUN samples): one photo each, its depth
    found and decoded with the dataset's encoding at a plausible indoor median."""
    from stages.app.pipeline import _folder_photos
    photos = {photo.id: photo for photo in _folder_photos(real / "rgbd")}
    assert sorted(photos) == ["NYU_color", "SUN_color", "TUM_color"]
    for name, fmt in (("NYU", "nyu"), ("SUN", "sun"), ("TUM", "tum")):
        depth_file = photos[f"{name}_color"].sidecars["depth"]
        assert depth_file.name.startswith(f"{name}_depth") and depth_formats.detect_sidecar_format(depth_file) == fmt
        depth = depth_formats.read_sidecar_depth(depth_file)
        assert 0.5 < float(np.median(depth[depth > 0])) < 6.0
