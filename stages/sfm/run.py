"""Stage `sfm`: posed, undistorted frames from the `frames` output with pycolmap (CPU).

Steps: SIFT extraction -> matching (sequential window, quadratic steps and loop closure, or exhaustive) ->
incremental mapping (largest model kept) -> undistortion to PINHOLE. When the default settings
register too few frames, a "robust" option set (more and affine-adapted features, guided
exhaustive matching, relaxed mapper inlier limits) is tried and the better model kept.

Output (docs/stage_contracts.md): `sparse/{cameras,images,points3D}.bin` (undistorted PINHOLE,
no `0/` folder), `images/` (undistorted frames, names as in sparse), `sfm.json` (with `source_camera`, the
camera refined on the frames before undistortion, and `bit_reproducible`).

One thread by default: pycolmap's multi-threaded extraction, matching and mapping give another model on every
run (point counts differing by tens, poses in the last digits), so one cache key would not mean one result.
Single-threaded, reruns are byte-identical; on the sample's 60 frames it cost about 10 % (22 s against 20-22 s).
"""
from __future__ import annotations

import logging
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import pycolmap

from stages.contract.errors import StageError
from stages.records.frames import FramesRecord
from stages.records.sfm import SfmRecord
from stages.sfm.spec import SfmConfig

if TYPE_CHECKING:  # the engine's object; not part of the stage's cache key
    from stages.engine.context import Context

log = logging.getLogger(__name__)


@dataclass
class MatchingPlan:
    """Which matcher a run uses and the explicit image pairs for the sequential one."""

    mode: str                                            # "sequential" | "exhaustive"
    pairs: list[tuple[str, str]] = field(default_factory=list)


@dataclass
class SfmAttempt:
    """The result of one extraction + matching + mapping pass."""

    reconstruction: pycolmap.Reconstruction | None
    matching: str
    robust: bool
    seconds: dict[str, float]


def sequential_pairs(names: list[str], overlap: int, loop_frames: int, quadratic: bool = False) -> list[tuple[str, str]]:
    """Pairs (i, i+1..i+overlap), with `quadratic` also (i, i + 2^k) beyond that window (a chain broken where a
    run of frames matches poorly is bridged), plus first-k x last-k loop-closure pairs, without repeats."""
    pairs: set[tuple[int, int]] = set()
    count = len(names)
    for i in range(count):
        for j in range(i + 1, min(count, i + overlap + 1)):
            pairs.add((i, j))
        step = 1
        while quadratic and i + step < count:
            if step > overlap:
                pairs.add((i, i + step))
            step *= 2
    k = min(loop_frames, count // 2)
    for i in range(k):
        for j in range(count - k, count):
            if j - i > overlap:
                pairs.add((i, j))
    return [(names[i], names[j]) for i, j in sorted(pairs)]


def plan_matching(names: list[str], cfg: SfmConfig, robust: bool) -> MatchingPlan:
    """Matching mode for this attempt: robust and short inputs match exhaustively."""
    mode = str(cfg.matching)
    if robust or (mode == "auto" and len(names) <= cfg.exhaustive_max_images):
        mode = "exhaustive"
    elif mode == "auto":
        mode = "sequential"
    pairs = (sequential_pairs(names, cfg.sequential_overlap, cfg.loop_closure_frames, cfg.quadratic_overlap)
             if mode == "sequential" else [])
    return MatchingPlan(mode, pairs)


def extraction_options(cfg: SfmConfig, robust: bool, threads: int) -> pycolmap.FeatureExtractionOptions:
    """SIFT options; robust = lower peak threshold, affine shape, domain-size pooling, own first octave."""
    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = threads
    options.use_gpu = False
    sift = options.sift
    sift.first_octave = cfg.robust_first_octave if robust else cfg.first_octave
    sift.peak_threshold = 0.002 if robust else cfg.peak_threshold
    sift.estimate_affine_shape = robust
    sift.domain_size_pooling = robust
    return options


def matching_options(guided: bool, threads: int) -> pycolmap.FeatureMatchingOptions:
    """Matcher options; `guided`: match again guided by each pair's two-view geometry."""
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = threads
    options.use_gpu = False
    options.guided_matching = guided
    return options


def mapping_options(cfg: SfmConfig, robust: bool, threads: int, seed: int) -> pycolmap.IncrementalPipelineOptions:
    """Incremental mapper options; known intrinsics are held fixed, robust relaxes inlier limits."""
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    options.random_seed = seed
    options.mapper.random_seed = seed
    options.mapper.num_threads = threads
    if cfg.intrinsics is not None:
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
        options.mapper.abs_pose_refine_focal_length = False
        options.mapper.abs_pose_refine_extra_params = False
    if robust:
        options.min_num_matches = 10
        options.mapper.init_min_num_inliers = 50
        options.mapper.init_min_tri_angle = 8.0
        options.mapper.abs_pose_min_num_inliers = 15
        options.mapper.abs_pose_min_inlier_ratio = 0.15
        options.mapper.max_reg_trials = 5
    return options


def reader_options(cfg: SfmConfig, scale: float) -> pycolmap.ImageReaderOptions:
    """One shared camera: fixed PINHOLE from known intrinsics (scaled to frame pixels), else cfg.camera_model."""
    options = pycolmap.ImageReaderOptions()
    if cfg.intrinsics is None:
        options.camera_model = cfg.camera_model
    else:
        if len(cfg.intrinsics) != 4:
            raise StageError(f"sfm: intrinsics must be [fx, fy, cx, cy], got {cfg.intrinsics}")
        options.camera_model = "PINHOLE"
        options.camera_params = ",".join(f"{scale * v:.6f}" for v in cfg.intrinsics)
    return options


def largest_model(models: dict[int, pycolmap.Reconstruction]) -> pycolmap.Reconstruction | None:
    """The reconstruction with the most registered images (None if there is none)."""
    return max(models.values(), key=lambda rec: rec.num_reg_images(), default=None)


def reconstruct(image_dir: Path, names: list[str], work: Path, cfg: SfmConfig, *, robust: bool,
                scale: float, threads: int, seed: int) -> SfmAttempt:
    """One full pass (extract, match, map) in `work`; returns the largest model and step times."""
    work.mkdir(parents=True, exist_ok=True)
    database = work / "database.db"
    seconds: dict[str, float] = {}
    pycolmap.set_random_seed(seed)

    start = time.perf_counter()
    pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader_options(cfg, scale),
                              extraction_options=extraction_options(cfg, robust, threads),
                              device=pycolmap.Device.cpu)
    seconds["extract"] = time.perf_counter() - start

    start = time.perf_counter()
    plan = plan_matching(names, cfg, robust)
    matcher = matching_options(robust or cfg.guided_matching, threads)
    if plan.mode == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matcher,
                                  device=pycolmap.Device.cpu)
    else:
        pairs_file = work / "pairs.txt"
        pairs_file.write_text("".join(f"{a} {b}\n" for a, b in plan.pairs))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = pairs_file
        pycolmap.match_image_pairs(database, matching_options=matcher,
                                   pairing_options=pairing, device=pycolmap.Device.cpu)
    seconds["match"] = time.perf_counter() - start

    start = time.perf_counter()
    models_dir = work / "models"
    models_dir.mkdir(exist_ok=True)
    models = pycolmap.incremental_mapping(database, image_dir, models_dir,
                                          options=mapping_options(cfg, robust, threads, seed))
    seconds["map"] = time.perf_counter() - start
    return SfmAttempt(largest_model(models), plan.mode, robust, seconds)


def registered_count(attempt: SfmAttempt) -> int:
    """Registered images of an attempt's model (0 without a model)."""
    return attempt.reconstruction.num_reg_images() if attempt.reconstruction is not None else 0


def check_quality(attempt: SfmAttempt, total: int, source: str, cfg: SfmConfig) -> float:
    """Quality gate; returns the mean reprojection error (px) or raises StageError naming `source`."""
    advice = ("film again with slower camera motion, more overlap between frames, "
              "and more texture in the scene (e.g. a patterned mat under the object)")
    registered = registered_count(attempt)
    if registered == 0:
        raise StageError(f"sfm: no camera model could be built from {source} ({total} frames): {advice}")
    error = attempt.reconstruction.compute_mean_reprojection_error()
    if registered / total < cfg.min_registered_ratio:
        raise StageError(f"sfm: only {registered} of {total} frames of {source} registered "
                         f"(< {cfg.min_registered_ratio:.0%}): {advice}")
    if error > cfg.max_reprojection_error_px:
        raise StageError(f"sfm: mean reprojection error {error:.2f} px for {source} is above "
                         f"{cfg.max_reprojection_error_px} px: {advice}")
    return error


def read_frames_folder(frames_dir: Path, min_frames: int) -> tuple[list[str], str, float]:
    """(image names, source description, source-to-frame scale) of a `frames` output folder."""
    image_dir = frames_dir / "images"
    index_file = frames_dir / FramesRecord.JSON
    if not index_file.is_file() or not image_dir.is_dir():
        raise StageError(f"sfm: {frames_dir} is not a frames output (needs images/ and frames.json); run the frames stage")
    entries = FramesRecord.read(frames_dir).frames
    names = [Path(entry.file).name for entry in entries]
    missing = [name for name in names if not (image_dir / name).is_file()]
    if missing:
        raise StageError(f"sfm: frames listed in {index_file} are missing from {image_dir}: {missing[:5]}")
    sources = sorted({entry.source for entry in entries})
    source = sources[0] if len(sources) == 1 else str(Path(sources[0]).parent)
    if len(names) < min_frames:
        raise StageError(f"sfm: {source} gave only {len(names)} frames, at least {min_frames} are needed; "
                         "use a longer video, more photos, or a smaller frames.motion_step")
    scale = entries[0].scale if entries else 1.0
    return names, source, scale


def run(ctx: Context) -> dict:
    """Pose the frames in `ctx.inputs["frames"]` and write the undistorted COLMAP model to ctx.out."""
    cfg = ctx.typed(SfmConfig)
    frames_dir = Path(ctx.inputs["frames"])
    names, source, scale = read_frames_folder(frames_dir, cfg.min_frames)
    image_dir = frames_dir / "images"
    threads = cfg.num_threads if cfg.num_threads > 0 else (os.cpu_count() or 1)
    # COLMAP's per-image INFO lines only when this module logs at DEBUG
    pycolmap.logging.minloglevel = 0 if log.isEnabledFor(logging.DEBUG) else int(pycolmap.logging.WARNING)
    total = len(names)

    with tempfile.TemporaryDirectory(prefix="sfm_work_", dir=ctx.out) as tmp:
        work = Path(tmp)
        attempts = [reconstruct(image_dir, names, work / "default", cfg, robust=False, scale=scale,
                                threads=threads, seed=ctx.seed)]
        log.info("sfm[%s]: default settings registered %d / %d", ctx.item, registered_count(attempts[0]), total)
        if cfg.robust_fallback and registered_count(attempts[0]) < cfg.robust_below_ratio * total:
            attempts.append(reconstruct(image_dir, names, work / "robust", cfg, robust=True, scale=scale,
                                        threads=threads, seed=ctx.seed))
            log.info("sfm[%s]: robust settings registered %d / %d", ctx.item, registered_count(attempts[1]), total)
        best = max(attempts, key=registered_count)
        error = check_quality(best, total, source, cfg)

        start = time.perf_counter()
        model_dir = work / "model"
        model_dir.mkdir()
        best.reconstruction.write(model_dir)
        undistorted = work / "undistorted"
        pycolmap.undistort_images(undistorted, model_dir, image_dir, output_type="COLMAP", num_threads=threads)
        undistort_seconds = time.perf_counter() - start
        camera = next(iter(pycolmap.Reconstruction(undistorted / "sparse").cameras.values()))
        rec = best.reconstruction
        source_camera = next(iter(rec.cameras.values()))
        registered_names = {rec.image(i).name for i in rec.reg_image_ids()}
        seconds = {step: sum(a.seconds[step] for a in attempts) for step in ("extract", "match", "map")}
        seconds["undistort"] = undistort_seconds
        summary = {
            "registered": len(registered_names),
            "total": total,
            "registered_ratio": len(registered_names) / total,
            "mean_reprojection_error_px": error,
            "points": rec.num_points3D(),
            "seconds": {k: round(v, 3) for k, v in seconds.items()},
            "matching": best.matching,
            "robust": best.robust,
            "attempts": [{"robust": a.robust, "matching": a.matching, "registered": registered_count(a)}
                         for a in attempts],
            "camera": {"model": camera.model_name, "width": camera.width, "height": camera.height,
                       "params": [float(v) for v in camera.params]},  # undistorted PINHOLE: fx, fy, cx, cy
            "source_camera": {"model": source_camera.model_name, "width": source_camera.width,  # the frames' camera
                              "height": source_camera.height, "params": [float(v) for v in source_camera.params]},
            "bit_reproducible": threads == 1,
            "unregistered": sorted(set(names) - registered_names),
            "source": source,
        }
        SfmRecord.write(ctx.out, summary, undistorted / "sparse", undistorted / "images")
    return summary
