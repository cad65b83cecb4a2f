"""Tests for stages/planes/run.py: synthetic rooms with known surfaces, the real TUM photo, bad input."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from stages.bg_depth import run as bg_depth
from stages.contract.errors import StageError
from stages.engine.context import Context
from stages.lib.geometry import fov_intrinsics
from stages.lib.planes import search as placement_planes
from stages.planes import run as planes
from stages.planes.spec import PlanesConfig
from stages.records.depth import DepthRecord

KINECT_K = [[525.0, 0.0, 320.0], [0.0, 525.0, 240.0], [0.0, 0.0, 1.0]]


def render_room(width: int = 320, height: int = 240, camera_height: float = 1.4, pitch_deg: float = 20.0,
                yaw_deg: float = 0.0, table: bool = True, floor: bool = True, wall_distance: float | None = 4.5,
                shelf_height: float | None = None, noise: float = 0.003, seed: int = 0,
                table_span: tuple[float, float, float] = (2.0, 3.0, 0.6)
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast a room (floor y=0, a table top at 0.75 m, a back wall, optionally a shelf top) seen
    by a pitched camera; without a wall, rays that hit nothing have no depth (0). The table top spans
    table_span = (near z, far z, half width) metres.

    World: y up, z forward (horizontal). Returns depth [H, W] metres (camera z), K [3, 3], support
    [H, W] int (0 none, 1 floor, 2 table, 4 shelf), true up [3] in the camera frame.
    """
    K = fov_intrinsics(width, height, 60.0)
    rows, cols = np.mgrid[0:height, 0:width]
    rays_cam = np.stack([(cols + 0.5 - K[0, 2]) / K[0, 0], (rows + 0.5 - K[1, 2]) / K[1, 1],
                         np.ones((height, width))], axis=-1)              # [H, W, 3], z = 1
    pitch, yaw = math.radians(pitch_deg), math.radians(yaw_deg)
    # camera axes in world coordinates (columns: camera x right, y down, z forward), pitched down
    forward = np.array([math.sin(yaw) * math.cos(pitch), -math.sin(pitch), math.cos(yaw) * math.cos(pitch)])
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    cam_to_world = np.stack([right, down, forward], axis=1)               # [3, 3]
    rays = rays_cam @ cam_to_world.T                                      # [H, W, 3] world dirs
    origin = np.array([0.0, camera_height, 0.0])
    best = np.full((height, width), np.inf)
    label = np.zeros((height, width), int)

    def hit(t: np.ndarray, mask: np.ndarray, surface: int) -> None:
        closer = mask & (t > 0) & (t < best)
        best[closer] = t[closer]
        label[closer] = surface

    with np.errstate(divide="ignore", invalid="ignore"):
        if floor:
            hit(-origin[1] / rays[..., 1], np.ones_like(best, bool), 1)
        if table:
            t = (0.75 - origin[1]) / rays[..., 1]
            p = origin + rays * t[..., None]
            near, far, half_width = table_span
            hit(t, (np.abs(p[..., 0]) < half_width) & (p[..., 2] > near) & (p[..., 2] < far), 2)
        if shelf_height is not None:
            t = (shelf_height - origin[1]) / rays[..., 1]
            p = origin + rays * t[..., None]
            hit(t, (np.abs(p[..., 0] - 1.0) < 0.5) & (p[..., 2] > 1.8) & (p[..., 2] < 2.8), 4)
        if wall_distance is not None:
            hit((wall_distance - origin[2]) / rays[..., 2], np.ones_like(best, bool), 3)
    depth = np.where(np.isfinite(best), best, 0.0)       # rays_cam has z = 1, so t = camera z
    depth *= 1.0 + noise * np.random.default_rng(seed).standard_normal(depth.shape)
    support = np.where(label == 3, 0, label)
    up = cam_to_world.T @ np.array([0.0, 1.0, 0.0])
    return depth.astype(np.float32), K, support, up


def angle_deg(a, b) -> float:
    return math.degrees(math.acos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def on_support_fraction(result_planes: list[dict], support: np.ndarray) -> float:
    pixels = np.concatenate([np.asarray(p["pixels"]) for p in result_planes])     # [N, 2] (u, v)
    return float((support[pixels[:, 1].astype(int), pixels[:, 0].astype(int)] > 0).mean())


def test_floor_and_table_found_wall_ignored():
    depth, K, support, true_up = render_room()
    result = placement_planes.find_placement_planes(depth, K, PlanesConfig(), np.random.default_rng(0))
    found = result["planes"]
    assert len(found) == 2, [p["center"] for p in found]
    assert angle_deg(result["up"], true_up) < 3.0
    heights = sorted(float(np.dot(p["center"], true_up)) for p in found)   # camera at 1.4 m
    assert heights[0] == pytest.approx(-1.4, abs=0.05) and heights[1] == pytest.approx(-0.65, abs=0.05)
    for plane in found:
        assert angle_deg(plane["normal"], true_up) < 3.0
    assert sum(len(p["points"]) for p in found) == 1000
    assert on_support_fraction(found, support) >= 0.97
    labels = result["labels"]
    assert (labels[support == 0] >= 0).mean() < 0.01          # the wall is not support


def monocular_like(depth: np.ndarray, seed: int = 0) -> np.ndarray:
    """Depth [H, W] as a monocular model gets it: bent by a slow warp (+-3 % across the photo) and with noise of
    1 % of the depth correlated over a pixel or two."""
    height, width = depth.shape
    v, u = np.mgrid[0:height, 0:width] / width
    warp = 0.03 * np.cos(2 * np.pi * 0.7 * (0.8 * u + 0.6 * v) + 1.0)
    noise = cv2.GaussianBlur(np.random.default_rng(seed).standard_normal((height, width)), (0, 0), 1.0)
    return (depth * np.exp(warp) * (1 + 0.01 * noise / noise.std())).astype(np.float32)


def test_gently_curved_noisy_floor_is_one_whole_plane():
    depth, K, support, true_up = render_room()
    result = placement_planes.find_placement_planes(monocular_like(depth), K, PlanesConfig(), np.random.default_rng(0))
    found = result["planes"]
    assert len(found) == 2 and angle_deg(result["up"], true_up) < 3.0
    heights = sorted(float(np.dot(p["center"], true_up)) for p in found)
    assert heights[0] == pytest.approx(-1.4, abs=0.05) and heights[1] == pytest.approx(-0.65, abs=0.05)
    assert all(angle_deg(p["normal"], true_up) < 3.0 for p in found)
    supported = result["labels"] >= 0
    assert supported[support == 1].mean() > 0.9 and supported[support == 2].mean() > 0.9   # whole, not scraps
    assert on_support_fraction(found, support) >= 0.97


def test_pixel_sampling_puts_points_nearer_than_area_sampling():
    depth, K, support, _ = render_room(table=False)
    found = {}
    for mode in ("area", "pixel"):
        cfg = PlanesConfig(point_sampling=mode)
        result = placement_planes.find_placement_planes(depth, K, cfg, np.random.default_rng(0))
        points = np.concatenate([p["points"] for p in result["planes"]])  # [N, 3] camera frame
        assert on_support_fraction(result["planes"], support) >= 0.97
        found[mode] = np.median(points[:, 2])
    assert found["pixel"] < 0.8 * found["area"]  # the floor's near part covers more pixels per square metre


def test_relative_depth_scale_does_not_change_the_planes():
    depth, K, support, true_up = render_room()
    result = placement_planes.find_placement_planes(depth / np.median(depth), K, PlanesConfig(), np.random.default_rng(0))
    assert len(result["planes"]) == 2 and angle_deg(result["up"], true_up) < 3.0
    assert on_support_fraction(result["planes"], support) >= 0.97


def test_plane_near_the_top_of_the_scene_is_dropped():
    depth, K, support, true_up = render_room(camera_height=3.0, pitch_deg=25.0, wall_distance=None, shelf_height=2.5)
    assert (support == 4).sum() > 2000
    shelf_height = -0.5                                   # relative to the camera, along true up
    kept = placement_planes.find_placement_planes(depth, K, PlanesConfig(), np.random.default_rng(0))
    everything = placement_planes.find_placement_planes(depth, K, PlanesConfig(top_drop_fraction=2.0),
                                              np.random.default_rng(0))
    heights = [float(np.dot(p["center"], true_up)) for p in everything["planes"]]
    assert any(abs(h - shelf_height) < 0.05 for h in heights)
    assert all(abs(float(np.dot(p["center"], true_up)) - shelf_height) > 0.3 for p in kept["planes"])
    assert len(kept["planes"]) == len(everything["planes"]) - 1


def test_plane_near_the_top_that_fills_the_photo_is_kept():
    """A close-up of a table top: the table is the top of the scene, and the photo's main surface."""
    depth, K, support, true_up = render_room(camera_height=1.4, pitch_deg=40.0, wall_distance=None,
                                             table_span=(0.5, 1.6, 0.7))
    assert (support == 2).mean() > 0.5
    kept = placement_planes.find_placement_planes(depth, K, PlanesConfig(), np.random.default_rng(0))
    heights = sorted(float(np.dot(p["center"], true_up)) for p in kept["planes"])
    assert heights == [pytest.approx(-1.4, abs=0.03), pytest.approx(-0.65, abs=0.03)]
    dropped = placement_planes.find_placement_planes(depth, K, PlanesConfig(top_keep_pixel_fraction=1.0),
                                                     np.random.default_rng(0))
    assert [float(np.dot(p["center"], true_up)) for p in dropped["planes"]] == [pytest.approx(-1.4, abs=0.03)]


def coloured_photo(support: np.ndarray, seed: int = 0) -> np.ndarray:
    """A photo [H, W, 3] uint8 of render_room's surfaces (support [H, W]): grey wall, green floor, red table, with
    pixel noise."""
    colours = np.array([(150, 150, 160), (40, 140, 60), (200, 60, 40), (0, 0, 0), (0, 0, 0)], float)
    noise = np.random.default_rng(seed).normal(0.0, 6.0, support.shape + (3,))
    return np.clip(colours[support] + noise, 0, 255).astype(np.uint8)


def test_colour_grows_a_table_top_that_blurred_depth_bends():
    """Estimated depth blurs the table's front edge into the floor: that part leaves the plane, but keeps the top's
    colour. The photo gives it back; measured depth is left as it is."""
    depth, K, support, _ = render_room()
    photo = coloured_photo(support)
    rng = np.random.default_rng(1)
    noise = cv2.GaussianBlur(rng.standard_normal(depth.shape), (0, 0), 1.0)
    blurred = (cv2.GaussianBlur(depth, (0, 0), 6.0) * (1 + 0.01 * noise / noise.std())).astype(np.float32)
    by_depth = placement_planes.find_placement_planes(blurred, K, PlanesConfig(), np.random.default_rng(0))["labels"]
    by_colour = placement_planes.find_placement_planes(blurred, K, PlanesConfig(), np.random.default_rng(0),
                                                       photo)["labels"]
    table = np.bincount(by_depth[support == 2][by_depth[support == 2] >= 0]).argmax()   # the table's plane
    assert (by_depth[support == 2] == table).mean() < 0.55
    assert (by_colour[support == 2] == table).mean() > (by_depth[support == 2] == table).mean() + 0.1
    grown = (by_colour >= 0) & (by_depth < 0)
    assert (support[grown] > 0).mean() > 0.7                  # mostly the surfaces, little of the wall
    measured = placement_planes.find_placement_planes(depth, K, PlanesConfig(), np.random.default_rng(0))
    with_photo = placement_planes.find_placement_planes(depth, K, PlanesConfig(), np.random.default_rng(0), photo)
    np.testing.assert_array_equal(measured["labels"], with_photo["labels"])


def test_wall_only_gives_no_planes():
    depth, K, _, _ = render_room(table=False, floor=False, pitch_deg=0.0, yaw_deg=25.0, wall_distance=3.0)
    assert (depth > 0).all()
    result = placement_planes.find_placement_planes(depth, K, PlanesConfig(), np.random.default_rng(0))
    assert result["planes"] == []


def test_subsampled_grid_keeps_the_geometry():
    depth = np.random.default_rng(0).uniform(1, 3, (240, 320)).astype(np.float32)
    K = fov_intrinsics(320, 240, 55.0)
    sub_depth, sub_K = placement_planes.subsample_depth(depth, K, 20000)                  # stride 2
    assert sub_depth.shape == (120, 160)
    rows, cols = np.array([0, 7, 119]), np.array([0, 100, 159])
    np.testing.assert_allclose(placement_planes.backproject(sub_depth, sub_K, rows, cols),
                               placement_planes.backproject(depth, K, rows * 2 + 1, cols * 2 + 1), rtol=1e-6)


def test_allocate_points_by_area_with_a_minimum():
    counts = placement_planes.allocate_points(np.array([90.0, 9.0, 0.5, 0.5]), 1000, 20)
    assert counts.sum() == 1000 and counts.min() == 20
    assert counts[0] > counts[1] > counts[2] == counts[3]
    assert placement_planes.allocate_points(np.array([3.0, 1.0]), 1000, 20).tolist() == [750, 250]


def test_hull_pca_up_of_a_tilted_box():
    rng = np.random.default_rng(1)
    box = rng.uniform([-3, -0.5, -2], [3, 0.5, 2], size=(4000, 3))   # flat along y
    tilt = math.radians(20)
    rotation = np.array([[1, 0, 0], [0, math.cos(tilt), -math.sin(tilt)], [0, math.sin(tilt), math.cos(tilt)]])
    up = placement_planes.hull_pca_up(box @ rotation.T + [0, 0, 5])
    assert angle_deg(up, rotation @ [0, -1, 0]) < 3.0


def run_stages(tmp_path: Path, depth: np.ndarray, K, photo: np.ndarray | None = None, seed: int = 3) -> dict:
    """bg_depth (npy sidecar) then planes; returns planes.json."""
    height, width = depth.shape
    image = tmp_path / "room.png"
    if photo is None:
        photo = np.full((height, width, 3), 128, np.uint8)
    cv2.imwrite(str(image), photo)
    np.save(tmp_path / "room_depth.npy", depth)
    depth_out, planes_out = tmp_path / "depth_out", tmp_path / "planes_out"
    depth_out.mkdir()
    planes_out.mkdir()
    bg_depth.run(Context("bg_depth", "room", {"K": np.asarray(K).tolist()},
                         {"image": image, "depth": tmp_path / "room_depth.npy"}, depth_out))
    metrics = planes.run(Context("planes", "room", {}, {"image": image, "depth": depth_out}, planes_out, seed=seed))
    assert metrics["planes"] == len(json.loads((planes_out / "planes.json").read_text())["planes"])
    placement = cv2.imread(str(planes_out / "placement.png"))
    assert placement.shape == (height, width, 3)
    return json.loads((planes_out / "planes.json").read_text())


def test_run_writes_contract_layout(tmp_path):
    depth, K, support, _ = render_room()
    record = run_stages(tmp_path, depth, K)
    assert set(record) == {"K", "width", "height", "up", "metric", "planes"}
    assert record["metric"] is True and (record["width"], record["height"]) == (320, 240)
    total = 0
    for plane in record["planes"]:
        assert set(plane) == {"normal", "center", "area", "points", "pixels"}
        points, pixels = np.array(plane["points"]), np.array(plane["pixels"])
        normal = np.array(plane["normal"])
        offset = normal @ np.array(plane["center"])
        assert np.abs(points @ normal - offset).max() < 1e-3          # points lie on their plane
        projected = points @ np.asarray(K).T
        assert np.allclose(projected[:, :2] / projected[:, 2:], pixels, atol=0.02)
        assert plane["area"] > 0 and len(points) >= 20
        total += len(points)
    assert total == 1000
    assert on_support_fraction(record["planes"], support) >= 0.97


def test_no_depth_provider_gives_empty_planes(tmp_path):
    image = tmp_path / "photo.png"
    cv2.imwrite(str(image), np.full((60, 80, 3), 90, np.uint8))
    depth_out, planes_out = tmp_path / "d", tmp_path / "p"
    depth_out.mkdir()
    planes_out.mkdir()
    bg_depth.run(Context("bg_depth", "photo", {"model": "none"}, {"image": image}, depth_out))  # no depth at all
    planes.run(Context("planes", "photo", {}, {"image": image, "depth": depth_out}, planes_out))
    assert json.loads((planes_out / "planes.json").read_text())["planes"] == []
    assert (planes_out / "placement.png").is_file()


def write_depth_folder(folder: Path, depth: np.ndarray, width: int, height: int) -> None:
    folder.mkdir()
    DepthRecord("sidecar", True, fov_intrinsics(width, height, 55.0), width, height, depth).write(folder)


@pytest.mark.parametrize("case", ["wrong_size", "all_zero", "no_record"])
def test_bad_depth_folder_is_a_clear_error(tmp_path, case):
    image = tmp_path / "photo.png"
    cv2.imwrite(str(image), np.full((60, 80, 3), 90, np.uint8))
    folder = tmp_path / "depth"
    depth = {"wrong_size": np.ones((30, 40), np.float32), "all_zero": np.zeros((60, 80), np.float32),
             "no_record": np.ones((60, 80), np.float32)}[case]
    write_depth_folder(folder, depth, 80, 60)
    if case == "no_record":
        (folder / "depth.json").unlink()
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(StageError, match="depth"):
        planes.run(Context("planes", "photo", {}, {"image": image, "depth": folder}, out))


def test_unreadable_photo_is_a_clear_error(tmp_path):
    image = tmp_path / "broken.png"
    image.write_bytes(b"not an image")
    folder = tmp_path / "depth"
    write_depth_folder(folder, np.ones((60, 80), np.float32), 80, 60)
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(StageError, match="broken.png"):
        planes.run(Context("planes", "photo", {}, {"image": image, "depth": folder}, out))


def tum_planes(tmp_path: Path, real: Path) -> tuple[dict, np.ndarray]:
    rgbd = real / "rgbd"
    depth_out, planes_out = tmp_path / "d", tmp_path / "p"
    depth_out.mkdir()
    planes_out.mkdir()
    bg_depth.run(Context("bg_depth", "TUM", {"K": KINECT_K},
                         {"image": rgbd / "TUM_color.png", "depth": rgbd / "TUM_depth.png"}, depth_out))
    planes.run(Context("planes", "TUM", {}, {"image": rgbd / "TUM_color.png", "depth": depth_out}, planes_out))
    return json.loads((planes_out / "planes.json").read_text()), np.load(depth_out / "depth.npy")


def test_real_tum_desk_and_floor(tmp_path, real):
    record, sensor_depth = tum_planes(tmp_path, real)
    up = np.array(record["up"])
    found = sorted(record["planes"], key=lambda p: np.dot(p["center"], up))
    floor = found[0]
    desk = [p for p in found if 0.6 < np.dot(np.subtract(p["center"], floor["center"]), up) < 0.85]
    assert floor["area"] > 1.0 and floor["pixels"] and np.mean(np.array(floor["pixels"])[:, 1]) > 300
    assert desk and max(p["area"] for p in desk) > 0.5                  # the desk top (0.73 m)
    on_desk_or_floor = (len(floor["points"]) + sum(len(p["points"]) for p in desk)) / 1000
    assert on_desk_or_floor >= 0.85
    # every placement point lies on the surface the sensor saw at its pixel
    points = np.concatenate([p["points"] for p in found])
    pixels = np.concatenate([p["pixels"] for p in found]).astype(int)
    measured = sensor_depth[pixels[:, 1], pixels[:, 0]]
    assert (np.abs(points[:, 2] - measured) < 0.05 * measured).mean() >= 0.95
