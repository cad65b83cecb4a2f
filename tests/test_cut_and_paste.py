"""cut_and_paste: cut-outs from rendered object masks, pasting, blend modes and the COCO output."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from stages.contract.errors import StageError
from stages.contract.fan_in import fan_in, input_name
from stages.cut_and_paste import run as cut_and_paste
from stages.engine.context import Context
from stages.lib.coco import load_coco, rle_to_mask
from stages.lib.composition.blend import motion_kernel, paste
from stages.lib.composition.cutouts import clean_mask, spread_indices
from stages.lib.composition.settings import BLEND_MODES
from stages.lib.gaussians.ply import write_ply
from stages.lib.gaussians.rasterize import render
from stages.lib.geometry import look_at_viewmat
from stages.records.cameras import CameraFrame, CamerasRecord
from stages.records.sfm import SfmRecord
from tests.factories.splats import make_blob

SIZE = 96
K = np.array([[90.0, 0.0, 48.0], [0.0, 90.0, 48.0], [0.0, 0.0, 1.0]])


def write_capture(root: Path, frames: int = 12) -> tuple[dict[str, Path], list[np.ndarray]]:
    """Object, splat and sfm folders of an orbit capture of the blob over grey; also the true masks."""
    g = make_blob()
    obj_dir, splat_dir, sfm_dir, staging = root / "extract", root / "splat", root / "sfm", root / "undistorted"
    for folder in (obj_dir, splat_dir, sfm_dir, staging / "images", staging / "sparse"):
        folder.mkdir(parents=True)
    write_ply(obj_dir / "object.ply", g)
    cameras, masks = [], []
    for k in range(frames):
        angle = 2 * np.pi * k / frames
        viewmat = look_at_viewmat(np.array([6 * np.cos(angle), 6 * np.sin(angle), 2.5]), np.array([0.0, 0.0, 1.0]))
        out = render(g, torch.as_tensor(viewmat, dtype=torch.float32), torch.as_tensor(K, dtype=torch.float32),
                     SIZE, SIZE, background=torch.full((3,), 0.5))
        rgb = (out.rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        cv2.imwrite(str(staging / "images" / f"{k:04d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cameras.append(CameraFrame(f"{k:04d}.png", K, viewmat, SIZE, SIZE))
        masks.append(out.alpha.numpy() > 0.5)
    CamerasRecord(SIZE, SIZE, cameras).write(splat_dir)
    camera = {"model": "PINHOLE", "width": SIZE, "height": SIZE, "params": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]}
    SfmRecord.write(sfm_dir, {"registered": frames, "total": frames, "camera": camera, "source_camera": camera},
                    staging / "sparse", staging / "images")
    background = root / "bg.png"
    cv2.imwrite(str(background), np.random.default_rng(0).integers(0, 255, (80, 120, 3), dtype=np.uint8))
    inputs = {**fan_in({"blob": {"object": obj_dir, "splat": splat_dir, "sfm": sfm_dir}}, cut_and_paste.INPUTS.object_kinds),
              **fan_in({"noise": {"background": background}}, cut_and_paste.INPUTS.photo_kinds)}
    return inputs, masks


def params(**overrides) -> dict:
    base = {"objects": [{"name": "blob", "height_m": 0.3}], "num_images": 8, "frames_per_object": 4,
            "min_cutout_pixels": 50, "preview_count": 4}
    base.update(overrides)
    return base


def test_spread_indices_and_mask_cleaning():
    assert spread_indices(100, 10) == [0, 11, 22, 33, 44, 55, 66, 77, 88, 99]
    assert spread_indices(3, 10) == [0, 1, 2]
    mask = np.zeros((20, 20), bool)
    mask[4:16, 4:16] = True
    mask[8:10, 8:10] = False  # a hole
    mask[0, 19] = True  # a speck
    cleaned = clean_mask(mask, 3)
    assert cleaned[4:16, 4:16].all() and cleaned.sum() == 144


def test_cutouts_match_the_rendered_object(tmp_path):
    inputs, masks = write_capture(tmp_path)
    category_id, cutouts = cut_and_paste.collect_cutouts(cut_and_paste.CutAndPasteConfig(**params()), inputs)["blob"]
    assert category_id == 1
    assert [c.source for c in cutouts] == ["0000.png", "0004.png", "0007.png", "0011.png"]
    for cutout, index in zip(cutouts, (0, 4, 7, 11)):
        truth = masks[index]
        assert abs(int(cutout.mask.sum()) - int(truth.sum())) <= 0.03 * truth.sum()
        box = (np.ptp(np.nonzero(truth.any(1))[0]) + 1, np.ptp(np.nonzero(truth.any(0))[0]) + 1)
        assert np.abs(np.subtract(cutout.mask.shape, box)).max() <= 2  # opening may trim a 1-px edge
        assert cutout.rgb.shape[:2] == cutout.mask.shape and cutout.rgb[cutout.mask].std() > 10  # object, not grey


def test_blend_modes_paste_inside_the_mask_only():
    image = np.zeros((40, 40, 3), np.float32)
    stripes = (np.arange(40) // 4 % 2).astype(np.float32)  # 4-px stripes: texture that Poisson keeps
    colour = np.repeat((0.5 + 0.5 * stripes)[None, :, None], 40, axis=0).repeat(3, axis=2)
    mask = np.zeros((40, 40), bool)
    mask[10:30, 12:28] = True
    for mode in BLEND_MODES:
        out = paste(image, colour, mask, mode, np.random.default_rng(0))
        assert out.shape == image.shape and np.isfinite(out).all()
        inside = out[15:25, 16:24]
        if mode == "poisson":  # gradient domain: the object's texture on the background's level
            assert inside.std() > 0.1
        else:
            assert inside.mean() > 0.6, mode  # object colour inside
        assert out[:4].max() < 0.05 and out[:, :6].max() < 0.05, mode  # background untouched far away
    assert np.array_equal(paste(image, colour, mask, "none", None)[..., 0] > 0.25, mask)
    assert np.isclose(motion_kernel(5, 0.3).sum(), 1.0)
    with pytest.raises(ValueError):
        paste(image, colour, mask, "fancy", None)


def test_later_pastes_shrink_earlier_masks():
    first = np.zeros((10, 10), bool)
    first[2:8, 2:8] = True
    second = np.zeros((10, 10), bool)
    second[5:10, 5:10] = True
    placed = [cut_and_paste.PlacedCutout(1, None, first, 36.0), cut_and_paste.PlacedCutout(1, None, second, 25.0)]
    visible = cut_and_paste.visible_masks(placed)
    assert visible[0].sum() == 36 - 9 and np.array_equal(visible[1], second)


def test_run_writes_valid_coco(tmp_path):
    inputs, _ = write_capture(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    stats = cut_and_paste.run(Context(stage="cut_and_paste", item="cp", params=params(), inputs=inputs, out=out, seed=3))
    coco = load_coco(out / "annotations.json")
    assert len(coco.getImgIds()) == 8 and len(coco.getAnnIds()) >= 8
    for ann in coco.loadAnns(coco.getAnnIds()):
        assert ann["area"] == int(rle_to_mask(ann["segmentation"]).sum()) > 0
        assert ann["blend"] in BLEND_MODES and 0.25 <= ann["visible_fraction"] <= 1.0
    assert stats["cutouts_per_object"] == {"blob": 4} and (out / "preview.png").is_file()


def test_missing_inputs_raise_clear_errors(tmp_path):
    inputs, _ = write_capture(tmp_path, frames=2)
    del inputs[input_name("sfm", "blob")]
    with pytest.raises(StageError, match="sfm:blob"):
        cut_and_paste.collect_cutouts(cut_and_paste.CutAndPasteConfig(**params()), inputs)
    with pytest.raises(StageError, match="blend_modes is empty"):
        cut_and_paste.CutAndPasteConfig(**params(blend_modes=[]))


def test_an_object_without_inputs_is_left_out_and_keeps_the_category_ids(tmp_path):
    inputs, _ = write_capture(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    objects = [{"name": "ghost", "height_m": 0.1}, {"name": "blob", "height_m": 0.3}]
    stats = cut_and_paste.run(Context(stage="cut_and_paste", item="cp", params=params(objects=objects), inputs=inputs,
                                      out=out, seed=3))
    coco = load_coco(out / "annotations.json")
    assert coco.getAnnIds() and {ann["category_id"] for ann in coco.loadAnns(coco.getAnnIds())} == {2}
    assert stats["left_out"] == {"object ghost": "no input given"} and stats["cutouts_per_object"] == {"blob": 4}
