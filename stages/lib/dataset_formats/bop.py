"""A compose dataset in the BOP format (BOP-scenewise, github.com/thodan/bop_toolkit docs/bop_datasets_format.md):
`<split>/<scene>/` with `rgb/`, `mask/` and `mask_visib/` (`<im>_<gt>.png`, 255 = object), `scene_camera.json`,
`scene_gt.json`, `scene_gt_info.json` and `scene_gt_coco.json`; `models/obj_<id>.ply` and
`models/models_info.json` when the objects' models are found (docs/stage_contracts.md, section "Dataset formats").

Scenes hold 1000 images each, like BOP's synthetic training sets. Object ids are the COCO category ids (1..);
poses are compose's `pose` (R, t of the object's metric frame: z up, origin at the centre of its 3-D box)
with t in millimetres, BOP's unit. The models are the objects' Gaussian means in that frame, in millimetres,
as point clouds: BOP's ADD / MSSD / MSPD errors use model points; its VSD error, which renders meshes, needs
a mesh these do not give. There are no depth images: the background's depth that compose used has no
objects in it (the COCO image entry names that file); `scene_camera.json` then has no `depth_scale`, and
`scene_gt_info.json` no `px_count_valid`. Masks are those of the image: `mask` is the amodal mask inside the
image, so `bbox_obj` is clipped to the image.
"""
from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path
from typing import Callable, Iterable

import cv2
import numpy as np
from scipy.spatial import ConvexHull
from scipy.spatial.distance import pdist

from stages.contract.errors import StageError
from stages.lib.coco import rle_box_and_area, rle_to_mask
from stages.records.coco_dataset import CocoDataset

log = logging.getLogger(__name__)

SCENE_IMAGES = 1000


def require_poses(dataset: CocoDataset, source: Path) -> None:
    """StageError unless every image has a camera K and every annotation a pose and an amodal mask."""
    for image in dataset.images:
        if "K" not in image:
            raise StageError(f"{source}: image {image['id']} has no camera K; the BOP export needs a compose "
                             "dataset (poses, camera, amodal masks)")
    for ann in dataset.annotations:
        if "pose" not in ann or "amodal_segmentation" not in ann:
            raise StageError(f"{source}: annotation {ann['id']} has no pose or amodal_segmentation; the BOP export "
                             "needs a compose dataset (poses, camera, amodal masks)")


MASK_PNG = [cv2.IMWRITE_PNG_BILEVEL, 1, cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY,
            cv2.IMWRITE_PNG_STRATEGY_RLE]  # 1 bit, fast zlib: a third of the time of OpenCV's 8-bit default


def write_mask(path: Path, rle: dict) -> None:
    """A mask given as COCO RLE as a 1-bit PNG (OpenCV reads it as 0 / 255, Pillow as bool)."""
    if not cv2.imwrite(str(path), rle_to_mask(rle).astype(np.uint8) * 255, MASK_PNG):
        raise StageError(f"cannot write {path} (is the disk full?)")


def instance_records(im_id: int, anns: list[dict]) -> tuple[list, list, list, list]:
    """scene_gt, scene_gt_info and scene_gt_coco entries of one image's instances, and their masks to write
    [(file relative to the scene, RLE)]."""
    gt, info, coco, masks = [], [], [], []
    for gt_id, ann in enumerate(anns):
        masks += [(f"mask/{im_id:06d}_{gt_id:06d}.png", ann["amodal_segmentation"]),
                  (f"mask_visib/{im_id:06d}_{gt_id:06d}.png", ann["segmentation"])]
        pose = ann["pose"]
        gt.append({"cam_R_m2c": np.asarray(pose["R"], dtype=np.float64).ravel().tolist(),
                   "cam_t_m2c": (1000.0 * np.asarray(pose["t"], dtype=np.float64)).round(3).tolist(),
                   "obj_id": int(ann["category_id"])})
        amodal_box, all_pixels = rle_box_and_area(ann["amodal_segmentation"])
        info.append({"bbox_obj": [int(v) for v in amodal_box], "bbox_visib": [int(v) for v in ann["bbox"]],
                     "px_count_all": all_pixels, "px_count_visib": int(ann["area"]),
                     "visib_fract": round(int(ann["area"]) / all_pixels, 6)})
        coco.append({"id": 0, "image_id": im_id, "category_id": int(ann["category_id"]), "iscrowd": 0,
                     "area": ann["area"], "bbox": ann["bbox"], "segmentation": ann["segmentation"]})
    return gt, info, coco, masks


def write_scene(scene: Path, folder: Path, images: list[dict], by_image: dict[int, list[dict]],
                categories: list[dict], progress: Callable[[Iterable], Iterable]) -> int:
    """One BOP scene of up to SCENE_IMAGES images; returns the instances written."""
    for sub in ("rgb", "mask", "mask_visib"):
        (scene / sub).mkdir(parents=True)
    cameras, gts, infos, masks = {}, {}, {}, []
    coco = {"images": [], "annotations": [], "categories": categories}
    for im_id, image in enumerate(progress(images)):
        rgb = f"rgb/{im_id:06d}{Path(image['file_name']).suffix}"
        shutil.copyfile(CocoDataset.image_file(folder, image), scene / rgb)
        cameras[str(im_id)] = {"cam_K": np.asarray(image["K"], dtype=np.float64).ravel().tolist()}
        gts[str(im_id)], infos[str(im_id)], anns, image_masks = instance_records(im_id, by_image[image["id"]])
        masks += [(scene / name, rle) for name, rle in image_masks]
        coco["images"].append({"id": im_id, "file_name": rgb, "width": image["width"], "height": image["height"]})
        coco["annotations"] += anns
    for path, rle in masks:  # one process: worker processes cost more to start than they save (export.md)
        write_mask(path, rle)
    for k, ann in enumerate(coco["annotations"]):
        ann["id"] = k
    for name, data in (("scene_camera", cameras), ("scene_gt", gts), ("scene_gt_info", infos), ("scene_gt_coco", coco)):
        (scene / f"{name}.json").write_text(json.dumps(data, indent=1))
    return len(coco["annotations"])


def point_model(path: Path, points_mm: np.ndarray) -> dict:
    """Write an ASCII PLY point cloud of points [N, 3] (millimetres); returns its models_info entry (the
    3-D box and the diameter: the largest distance between two points, found on their convex hull)."""
    header = f"ply\nformat ascii 1.0\nelement vertex {len(points_mm)}\nproperty float x\nproperty float y\n" \
             "property float z\nend_header\n"
    path.write_text(header + "%.3f %.3f %.3f\n" * len(points_mm) % tuple(points_mm.ravel()))
    hull = points_mm[ConvexHull(points_mm).vertices]
    diameter = float(pdist(hull).max())
    low, high = points_mm.min(axis=0), points_mm.max(axis=0)
    return {"diameter": round(diameter, 3), "min_x": round(float(low[0]), 3), "min_y": round(float(low[1]), 3),
            "min_z": round(float(low[2]), 3), "size_x": round(float(high[0] - low[0]), 3),
            "size_y": round(float(high[1] - low[1]), 3), "size_z": round(float(high[2] - low[2]), 3)}


def export_bop(folder: Path, dataset: CocoDataset, out: Path, split: str = "train",
               models: dict[str, np.ndarray] | None = None,
               progress: Callable[[Iterable], Iterable] = lambda items: items) -> dict:
    """Export the compose dataset in `folder` (read as `dataset`) into out/<split>/<scene>/ (and out/models/ from
    `models`: {object name: its points [N, 3] in metres in the poses' frame}). Returns counts."""
    require_poses(dataset, folder / CocoDataset.JSON)
    by_image = dataset.annotations_by_image()
    categories = [{"id": c["id"], "name": c["name"], "supercategory": c.get("supercategory", "object")}
                  for c in dataset.categories]
    instances = 0
    for start in range(0, len(dataset.images), SCENE_IMAGES):
        scene = out / split / f"{start // SCENE_IMAGES:06d}"
        instances += write_scene(scene, folder, dataset.images[start:start + SCENE_IMAGES], by_image, categories,
                                 progress)
    ids = {c["name"]: c["id"] for c in dataset.categories}
    if models:
        (out / "models").mkdir(parents=True)
        info = {str(ids[name]): point_model(out / "models" / f"obj_{ids[name]:06d}.ply", 1000.0 * points)
                for name, points in models.items()}
        (out / "models" / "models_info.json").write_text(json.dumps(info, indent=1))
    summary = {"split": split, "scenes": -(-len(dataset.images) // SCENE_IMAGES), "images": len(dataset.images),
               "instances": instances, "models": sorted(models or {})}
    log.info("BOP export: %s", summary)
    return summary
