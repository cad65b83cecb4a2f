"""A user's own data (data.source: folder) as a new user brings it, with the mistakes they make: object videos,
a folder of background photos with depth sidecars, COCO test sets, and the data config file that lists them.

`write_user_data(root, defects)` writes the good items and, for each named defect, one bad item among them:

- corrupt_video:    object `broken` whose video is random bytes
- missing_video:    object `ghost` whose video path does not exist
- truncated_photo:  background `torn.jpg` cut off after half of its bytes
- tum_plain_name:   background `office` whose depth is TUM-encoded (metres = value / 5000) but named
                    `office.depth.png` (read as millimetres)
- photo_without_depth: background `hall` with no depth sidecar
- bad_annotations:  test set `test_bad` whose annotations.json is not JSON
- wrong_categories: test set `test_names` whose category is `cup` (no such object)
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from stages.lib.coco import CocoBuilder
from tests.factories.backgrounds import corner_wall_depth
from tests.factories.media import noise_video, write_image

DEFECTS = ("corrupt_video", "missing_video", "truncated_photo", "tum_plain_name", "photo_without_depth",
           "bad_annotations", "wrong_categories")
GOOD_OBJECTS = ("mug", "can")
WIDTH, HEIGHT = 96, 72
K = np.array([[0.9 * WIDTH, 0.0, WIDTH / 2], [0.0, 0.9 * WIDTH, HEIGHT / 2], [0.0, 0.0, 1.0]])


def _photo(seed: int) -> np.ndarray:
    """A textured BGR uint8 photo [HEIGHT, WIDTH, 3]."""
    return np.random.default_rng(seed).integers(40, 220, (HEIGHT, WIDTH, 3), dtype=np.uint8)


def _depth_m() -> np.ndarray:
    """A room corner 2.5 m ahead: float32 [HEIGHT, WIDTH] metres (median about 2.1 m)."""
    return corner_wall_depth(WIDTH, HEIGHT, K, corner_distance=2.5)


def _testset(folder: Path, category: str) -> None:
    """A one-image COCO test set of `category` in `folder` (images/ + annotations.json)."""
    (folder / "images").mkdir(parents=True)
    write_image(folder / "images" / "0000.png", _photo(7))
    builder = CocoBuilder([category])
    image_id = builder.add_image("0000.png", WIDTH, HEIGHT)
    mask = np.zeros((HEIGHT, WIDTH), bool)
    mask[20:50, 30:60] = True
    builder.add_instance(image_id, 1, mask)
    builder.dataset.write(folder)


def write_user_data(root: Path, defects: tuple[str, ...] = ()) -> Path:
    """Write the data under `root` and its data config `root/my_data.yaml` (absolute paths); returns the file."""
    unknown = set(defects) - set(DEFECTS)
    assert not unknown, f"unknown defects {unknown}; known: {DEFECTS}"
    videos, photos = root / "videos", root / "photos"
    videos.mkdir(parents=True)
    photos.mkdir()
    objects = [{"name": name, "height_m": 0.1, "video": str(noise_video(videos / f"{name}.mp4", 10, WIDTH, HEIGHT, k))}
               for k, name in enumerate(GOOD_OBJECTS)]
    if "corrupt_video" in defects:
        (videos / "broken.mp4").write_bytes(np.random.default_rng(0).bytes(4096))
        objects.append({"name": "broken", "height_m": 0.1, "video": str(videos / "broken.mp4")})
    if "missing_video" in defects:
        objects.append({"name": "ghost", "height_m": 0.1, "video": str(videos / "ghost.mp4")})

    write_image(photos / "kitchen.png", _photo(1))
    write_image(photos / "kitchen.depth.png", np.rint(_depth_m() * 1000).astype(np.uint16))
    if "truncated_photo" in defects:
        full = write_image(photos / "torn.jpg", _photo(2)).read_bytes()
        (photos / "torn.jpg").write_bytes(full[: len(full) // 2])
    if "tum_plain_name" in defects:
        write_image(photos / "office.png", _photo(3))
        write_image(photos / "office.depth.png", np.rint(_depth_m() * 5000).astype(np.uint16))
    if "photo_without_depth" in defects:
        write_image(photos / "hall.png", _photo(4))

    test_sets = [{"name": "test", "path": str(root / "test")}]
    _testset(root / "test", GOOD_OBJECTS[0])
    if "bad_annotations" in defects:
        _testset(root / "test_bad", GOOD_OBJECTS[0])
        (root / "test_bad" / "annotations.json").write_text('{"images": [')
        test_sets.append({"name": "test_bad", "path": str(root / "test_bad")})
    if "wrong_categories" in defects:
        _testset(root / "test_names", "cup")
        test_sets.append({"name": "test_names", "path": str(root / "test_names")})

    config = root / "my_data.yaml"
    config.write_text(yaml.safe_dump({"source": "folder", "objects": objects, "backgrounds": str(photos),
                                      "test_sets": test_sets}))
    return config

