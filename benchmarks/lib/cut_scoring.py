"""Scoring a cut of a trained splat against the sample's ground truth (benchmarks/extract.py `trained`, the capture
benchmark): align the splat's frame to the world, which Gaussians are the object, the cut's precision and recall
and its mask IoU at the held-out capture views (the figures: benchmarks/extract.py's module doc); the panel of a
refused cut; the self-check's share of extract's time; the entries a cached splat was made from.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import torch

from benchmarks.lib.evaluation import angle_deg, score, umeyama_similarity
from benchmarks.lib.truth_views import TruthViews, raycasting_scene, supported_truth, visible_iou
from stages.engine.cache_entry import read_manifest
from stages.extract.run import draw_filtering
from stages.extract.spec import ExtractConfig
from stages.lib.gaussians.model import SH_C0, Gaussians
from stages.lib.gaussians.ply import read_ply
from stages.lib.gaussians.rasterize import render
from stages.lib.geometry import camera_centres
from stages.lib.objects.cut import STEPS, Extraction, cut_gaussians
from stages.lib.objects.pointcloud import nearest_distance
from stages.lib.objects.self_check import cut_figures
from stages.lib.objects.silhouettes import Intrinsics
from stages.lib.sample_scene.capture import capture_rng
from stages.lib.sample_scene.meshes import Mesh, sample_surface
from stages.lib.sample_scene.objects import build_object
from stages.records.cameras import CamerasRecord
from stages.records.capture_truth import CaptureTruth
from stages.records.frames import FramesRecord

BOTTOM_SLICE_M = 0.02
CUT_TARGETS = {"precision": 0.95, "recall": 0.90, "mask_iou_min": 0.90}  # a cut within the capture benchmark's targets


def align_to_world(cameras: CamerasRecord, gt: CaptureTruth, frames_dir: Path | None) -> tuple[float, np.ndarray, np.ndarray, dict]:
    """Similarity (scale, R [3, 3], t [3]) taking the model frame to the GT world frame, fitted to the
    camera centres of cameras.json against gt.json, and the GT frame index of each cameras.json file."""
    source_index = {}
    if frames_dir is not None:
        source_index = {Path(entry.file).name: entry.source_index for entry in FramesRecord.read(frames_dir).frames}
    index_of, model_centres, world_centres = {}, [], []
    for frame in cameras.frames:
        index = source_index.get(Path(frame.file).name, int(Path(frame.file).stem))
        if index in gt.viewmats:
            index_of[frame.file] = index
            model_centres.append(camera_centres(frame.viewmat))
            world_centres.append(camera_centres(gt.viewmats[index]))
    if len(model_centres) < 3:
        raise SystemExit(f"only {len(model_centres)} cameras.json frames match gt.json frames; cannot align")
    scale, rotation, shift = umeyama_similarity(np.asarray(model_centres), np.asarray(world_centres))
    return scale, rotation, shift, index_of


def gt_object_meshes(gt: CaptureTruth, object_points: np.ndarray) -> list[Mesh]:
    """The sample object's meshes in the GT world, rebuilt from its generator (name, height, seed) and
    checked against object_points.npy (the same surface samples must come out)."""
    meshes = build_object(gt.name, gt.height_m, gt.seed)
    resampled = sample_surface(meshes, len(object_points), capture_rng(gt.seed, gt.name + "/points"))
    if not np.allclose(resampled, object_points, atol=1e-6):
        raise SystemExit(f"the rebuilt {gt.name} meshes do not reproduce object_points.npy: the sample "
                         "generator changed since this sample was made; regenerate the sample")
    return meshes


def inside_meshes(meshes: list[Mesh], points: np.ndarray, rays: int = 11) -> np.ndarray:
    """Mask [N] of points [N, 3] inside the union of `meshes`: ray-parity occupancy (Open3D), majority
    of `rays` random rays, so a ray grazing an edge or a small seam between parts does not decide."""
    occupancy = raycasting_scene(meshes).compute_occupancy(o3d.core.Tensor(points.astype(np.float32)), nsamples=rays)
    return occupancy.numpy() > 0.5


def visual_hull_votes(points: np.ndarray, gt: CaptureTruth, gt_dir: Path) -> np.ndarray:
    """Fraction [N] of the GT views whose object mask contains the projection of each point [N, 3]
    (a cross-check of the volume test: 1.0 = inside the visual hull of all masks)."""
    votes = np.zeros(len(points))
    for index, viewmat in gt.viewmats.items():
        camera = points @ viewmat[:3, :3].T + viewmat[:3, 3]  # [N, 3]
        pixels = np.floor((camera @ gt.K.T)[:, :2] / np.maximum(camera[:, 2:3], 1e-9)).astype(np.int64)  # [N, 2]
        mask = cv2.imread(str(gt_dir / "masks" / f"{index:04d}.png"), cv2.IMREAD_GRAYSCALE) > 127
        seen = (camera[:, 2] > 0) & (pixels[:, 0] >= 0) & (pixels[:, 0] < gt.width) & (pixels[:, 1] >= 0) & (pixels[:, 1] < gt.height)
        votes[seen] += mask[pixels[seen, 1], pixels[seen, 0]]
    return votes / len(gt.viewmats)


def enclosed_sideways(meshes: list[Mesh], points: np.ndarray, up: np.ndarray, rays: int = 16) -> np.ndarray:
    """Mask [N] of points [N, 3] that every one of `rays` horizontal rays (perpendicular to `up` [3], evenly spaced)
    sends into `meshes`: inside a container's cavity (a vase's, open only at the top), where what a camera sees
    through the opening is the object's inside."""
    up = up / np.linalg.norm(up)
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    other = np.cross(up, side)
    scene = raycasting_scene(meshes)
    hit = np.ones(len(points), dtype=bool)
    for angle in np.linspace(0.0, 2.0 * np.pi, rays, endpoint=False):
        direction = np.cos(angle) * side + np.sin(angle) * other  # [3]
        cast = np.concatenate([points, np.broadcast_to(direction, points.shape)], axis=1).astype(np.float32)  # [N, 6]
        hit &= np.isfinite(scene.cast_rays(o3d.core.Tensor(cast))["t_hit"].numpy())
    return hit


def object_membership(world: np.ndarray, gt: CaptureTruth, object_points: np.ndarray, meshes: list[Mesh],
                      object_distance: float) -> dict:
    """Which Gaussians (world means [N, 3], metres, support plane z = 0 along gt ground_normal) are object;
    object_points [M, 3] and meshes: the object's surface samples and meshes (`gt_object_meshes`).

    `near`: within object_distance of a surface sample and not below the support plane (floor Gaussians
    next to the object's base are floor); `inside`: inside the GT meshes and above the support plane (only
    Gaussians within 5 cm of the surface are tested); `cavity`: between the support plane and the object's top, and
    enclosed by the object on every side (`enclosed_sideways`): in a vase's
    cavity, where Gaussians render the inside seen through its mouth and no other surface is;
    `is_object` = near | inside | cavity.
    """
    heights = (world - gt.ground_point) @ gt.ground_normal  # [N]
    distance = nearest_distance(world, object_points)  # [N]
    near = (distance < object_distance) & (heights >= 0)
    top = float(((object_points - gt.ground_point) @ gt.ground_normal).max())
    candidates = np.flatnonzero((distance < 0.05) & (heights >= 0))
    inside = np.zeros(len(world), dtype=bool)
    inside[candidates] = inside_meshes(meshes, world[candidates])
    cavity = np.zeros(len(world), dtype=bool)
    open_candidates = np.flatnonzero((heights >= 0) & (heights <= top) & ~near & ~inside)
    cavity[open_candidates] = enclosed_sideways(meshes, world[open_candidates], gt.ground_normal)
    return {"near": near, "inside": inside, "cavity": cavity, "is_object": near | inside | cavity}


def below_bottom_px(predicted: np.ndarray, truth: np.ndarray) -> float:
    """Mean rows of a predicted mask [H, W] bool under the lowest pixel of the true mask [H, W] bool, over the
    columns the true mask covers: a fringe that runs below the object's base (0 when there is none)."""
    covered = truth.any(axis=0)                                                                   # [W]
    lowest = truth.shape[0] - 1 - np.argmax(truth[::-1], axis=0)                                  # [W]
    below = predicted & (np.arange(truth.shape[0])[:, None] > lowest[None, :]) & covered[None, :]
    return float(below.sum() / max(int(covered.sum()), 1))


def mask_scores(world_object: Gaussians, truth: TruthViews, indices: list[int],
                threshold: float = 0.5) -> tuple[list[float], list[float], list[np.ndarray]]:
    """IoU of the object's rendered opacity (> threshold) with the true visible masks at the given GT frames,
    over the pixels where nothing else hides the object, the rows it runs below their bottom
    (below_bottom_px), and the rendered masks [H, W] bool, per frame."""
    gt = truth.gt
    K = torch.tensor(gt.K, dtype=torch.float32)
    white = torch.ones(world_object.num, 3)
    ious, below, masks = [], [], []
    for index in indices:
        alpha = render(world_object, torch.tensor(gt.viewmats[index], dtype=torch.float32), K, gt.width, gt.height,
                       colors=white).alpha.detach().numpy()  # [H, W]
        visible, hidden = truth.masks(index)  # [H, W], [H, W]
        predicted = alpha > threshold
        ious.append(visible_iou(predicted, visible, hidden))
        below.append(below_bottom_px(predicted & ~hidden, visible))
        masks.append(predicted)
    return ious, below, masks


def missed_share_under_support(world_splat: Gaussians, under: np.ndarray, truth: TruthViews, index: int,
                               predicted: np.ndarray) -> float:
    """Of the seen true-mask pixels a cut misses at GT frame `index` (predicted [H, W] bool), the share the whole
    splat (world_splat, in the GT world) draws with Gaussians centred under the support plane (under [N] bool):
    parts of the object the splat drew as floor, which no cut above the plane can keep."""
    gt = truth.gt
    colours = torch.from_numpy(np.stack([under, ~under, np.zeros_like(under)], axis=1).astype(np.float32))  # [N, 3]
    drawn = render(world_splat, torch.tensor(gt.viewmats[index], dtype=torch.float32), torch.tensor(gt.K, dtype=torch.float32),
                   gt.width, gt.height, colors=colours).rgb.detach().numpy()  # [H, W, 3] on black
    visible, hidden = truth.masks(index)
    missed = visible & ~predicted & ~hidden
    return float(drawn[missed, 0].sum() / max(drawn[missed, :2].sum(), 1e-9))


def self_check_seconds(gaussians: Gaussians, cameras: CamerasRecord, extraction: Extraction,
                       cfg: ExtractConfig) -> float:
    """Seconds the self-check's figures of a finished cut take (stages/lib/objects/self_check.py cut_figures,
    recomputed from the cut as extract computes them)."""
    means = gaussians.means.detach().cpu().numpy().astype(np.float64)
    opacities = gaussians.opacities.detach().cpu().numpy()
    intrinsics = Intrinsics.of_cameras(cameras)
    start = time.perf_counter()
    points = (means - extraction.centre) / extraction.scene_scale  # [N, 3]
    solid = extraction.keep & (opacities >= cfg.height_opacity)
    cut_figures(points, solid, len(means), int(extraction.keep.sum()), extraction.normal,
                extraction.height / extraction.scene_scale, cameras.viewmats, intrinsics.Ks, intrinsics.sizes,
                np.zeros(3), extraction.scene_scale, extraction.centre)
    return time.perf_counter() - start


def within_targets(figures: dict) -> bool:
    """Whether a cut's figures (precision, recall, mask_iou_min) meet CUT_TARGETS."""
    return all(figures[key] >= target for key, target in CUT_TARGETS.items())


def splat_chain(cache: Path, splat_key: str) -> tuple[Path, Path, Path, Path]:
    """(splat_train, sfm and frames entries, the sample's capture folder) of the splat `splat_key` in `cache`, from
    the manifests of the entries it was made from, whichever checkout keyed them."""
    splat = cache / "splat_train" / splat_key
    if not (splat / "manifest.json").is_file():
        raise SystemExit(f"{splat}: no splat_train entry there; give the --cache that trained the rows' splats")
    sfm = cache / "sfm" / read_manifest(splat)["inputs"]["sfm"]
    frames = cache / "frames" / read_manifest(sfm)["inputs"]["frames"]
    video = Path(read_manifest(frames)["inputs"]["video"])  # <sample key>/objects/<name>/video.mp4
    return splat, sfm, frames, cache / "sample" / video.parent


@dataclass
class SplatTruth:
    """A trained splat folder beside the sample's ground truth of its capture, computed once for any number of cuts:
    the splat in the world frame and which of its Gaussians are the object (object_membership)."""

    gt: CaptureTruth  # with its support plane at the object's support (supported_truth)
    support_rise: float
    cameras: CamerasRecord
    scale: float
    rotation: np.ndarray  # [3, 3] model to world (with scale and shift)
    shift: np.ndarray  # [3]
    gaussians: Gaussians  # as trained (model frame)
    world: np.ndarray  # [N, 3] the Gaussians' means in the world frame
    membership: dict  # object_membership
    truth: TruthViews
    held_out: list[int]  # the held-out frames scored (TruthViews.scored_views) ...
    hidden_views: list[int]  # ... and those showing under MIN_VISIBLE of the object
    aligned: int  # cameras aligned to gt's frames

    @classmethod
    def read(cls, splat: Path, gt_dir: Path, frames_dir: Path | None, object_distance: float) -> "SplatTruth":
        """The splat folder `splat` against the capture folder `gt_dir` (frames_dir: its frames entry)."""
        gt, support_rise = supported_truth(CaptureTruth.read(gt_dir))
        cameras = CamerasRecord.read(splat)
        scale, rotation, shift, index_of = align_to_world(cameras, gt, frames_dir)
        gaussians = read_ply(splat / "scene.ply")
        world = scale * gaussians.means.detach().cpu().numpy().astype(np.float64) @ rotation.T + shift
        object_points = gt.object_points(gt_dir)
        meshes = gt_object_meshes(gt, object_points)  # [the object's parts], checked against object_points
        truth = TruthViews(gt, gt_dir, meshes)
        held_out, hidden = truth.scored_views([index_of[name] for name in cameras.held_out if name in index_of])
        return cls(gt, support_rise, cameras, scale, rotation, shift, gaussians, world,
                   object_membership(world, gt, object_points, meshes, object_distance), truth, held_out, hidden,
                   len(index_of))

    @cached_property
    def world_splat(self) -> Gaussians:
        """The splat moved into the world frame."""
        return self.gaussians.transformed(torch.tensor(self.rotation, dtype=torch.float32),
                                          torch.tensor(self.shift, dtype=torch.float32), self.scale)

    def ious(self, keep: np.ndarray) -> tuple[list[float], list[float], list[np.ndarray]]:
        """mask_scores of the Gaussians `keep` [N] bool at the scored held-out views."""
        return mask_scores(self.world_splat.subset(torch.from_numpy(keep)), self.truth, self.held_out)


def bench_trained(splat: Path, gt_dir: Path, frames_dir: Path | None, object_distance: float,
                  cfg: ExtractConfig, seed: int = 0, enforce_checks: bool = True) -> dict:
    """Score extract on a trained splat folder against the sample's ground truth (see module doc); `seed`:
    RANSAC's (the extract node's own seed gives the stage's cut). enforce_checks=False scores a cut the checks
    refuse too (its checks["refused"] says why)."""
    scene = SplatTruth.read(splat, gt_dir, frames_dir, object_distance)
    gt, world, membership, gaussians, cameras = scene.gt, scene.world, scene.membership, scene.gaussians, scene.cameras
    is_object = membership["is_object"]
    start = time.perf_counter()
    extraction = cut_gaussians(gaussians, cfg, cameras, seed=seed, enforce_checks=enforce_checks)
    seconds = time.perf_counter() - start
    ious, below, masks = scene.ious(extraction.keep)
    true_cut, true_cut_below, _ = scene.ious(is_object)  # the ground truth's own cut of this splat, for reference
    heights = (world - gt.ground_point) @ gt.ground_normal  # [N] m
    worst = int(np.argmin(ious)) if ious else None
    bottom = heights < BOTTOM_SLICE_M  # recall of the object's lowest slice: is its base cut off?
    surface = score(extraction.keep, membership["near"])
    false_surface = extraction.keep & ~membership["near"]  # [N] the surface-only test's false positives
    hull = visual_hull_votes(world[false_surface], gt, gt_dir)
    false_in_hull = hull[~is_object[false_surface]] >= 1.0  # the cut's false positives (within false_surface)
    return {"scene": str(splat), **score(extraction.keep, is_object),
            "precision_surface": surface["precision"], "recall_surface": surface["recall"],
            "surface_false_positives": int(false_surface.sum()),
            "of_which_inside_volume": int((false_surface & membership["inside"]).sum()),
            "kept_in_cavity": int((extraction.keep & membership["cavity"]).sum()),
            "of_which_in_visual_hull": int((hull >= 1.0).sum()),
            "false_in_visual_hull": float(false_in_hull.mean()) if len(false_in_hull) else 0.0,
            "normal_error_deg": angle_deg(scene.rotation @ extraction.normal, gt.ground_normal),
            "height_m": extraction.height * scene.scale, "gt_height_m": gt.height_m,
            "support_above_gt_plane_m": scene.support_rise,
            "kept_min_height_m": float(heights[extraction.keep].min()),
            "bottom_recall": score(extraction.keep[bottom], is_object[bottom])["recall"],
            "mask_iou_mean": float(np.mean(ious)) if ious else None, "mask_iou_min": float(np.min(ious)) if ious else None,
            "mask_iou_min_true_cut": float(np.min(true_cut)) if true_cut else None,
            "worst_view_missed_under_support": None if worst is None else missed_share_under_support(
                scene.world_splat, heights < 0, scene.truth, scene.held_out[worst], masks[worst]),
            "mask_below_bottom_px": float(np.median(below)) if below else None,
            "mask_below_bottom_px_true_cut": float(np.median(true_cut_below)) if true_cut_below else None,
            "held_out_views": len(ious), "held_out_views_hidden": scene.hidden_views,
            "cameras_aligned": scene.aligned, "plane_source": extraction.plane_source,
            "missed_by_step": {step: int((is_object & (extraction.removed_by == index)).sum())
                               for index, step in enumerate(STEPS) if index > 0},
            "counts": extraction.counts, "checks": extraction.checks, "seconds": seconds,
            "self_check_seconds": self_check_seconds(gaussians, cameras, extraction, cfg)}


def draw_cut_panel(splat: Path, path: Path, cfg: ExtractConfig, seed: int = 0) -> dict:
    """The filtering panel of extract's cut of a trained splat folder, made with its checks off (a refused cut's
    too); returns the checks (their figures and, under "refused", the message). A StageError of an earlier step
    still propagates."""
    gaussians = read_ply(splat / "scene.ply")
    means = gaussians.means.detach().cpu().numpy()
    extraction = cut_gaussians(gaussians, cfg, CamerasRecord.read(splat), seed=seed, enforce_checks=False)
    draw_filtering(path, means, 0.5 + SH_C0 * gaussians.sh[:, 0].detach().cpu().numpy(), extraction)
    return extraction.checks
