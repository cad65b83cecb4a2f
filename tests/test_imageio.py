"""The photo loader and image listing (stages/lib/imageio.py)."""
from __future__ import annotations

import numpy as np
import pytest

from stages.contract.errors import StageError
from stages.lib.imageio import IMAGE_SUFFIXES, list_images, load_photo
from tests.factories.media import write_image


def test_photo_conversions(tmp_path):
    gray = write_image(tmp_path / "gray.png", np.full((40, 50), 77, np.uint8))
    assert (load_photo(gray) == 77).all() and load_photo(gray).shape == (40, 50, 3)
    rgba = write_image(tmp_path / "rgba.png", np.dstack([np.full((40, 50, 3), (10, 20, 30), np.uint8),
                                                         np.full((40, 50), 5, np.uint8)]))
    assert load_photo(rgba)[0, 0].tolist() == [30, 20, 10]          # BGR on disk
    sixteen = write_image(tmp_path / "g16.png", np.full((40, 50), 257 * 200, np.uint16))
    assert (load_photo(sixteen) == 200).all()
    rgb16 = write_image(tmp_path / "rgb16.png", np.full((40, 50, 3), 257 * 100, np.uint16))
    assert (load_photo(rgb16) == 100).all()


def test_bad_photos(tmp_path):
    tiny = write_image(tmp_path / "tiny.png", np.zeros((10, 12, 3), np.uint8))
    with pytest.raises(StageError, match="tiny.png.*too small"):
        load_photo(tiny)
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(b"\xff\xd8 truncated")
    with pytest.raises(StageError, match="broken.jpg"):
        load_photo(broken)


def test_list_images_takes_every_image_suffix_in_any_case(tmp_path):
    for index, suffix in enumerate(IMAGE_SUFFIXES):
        (tmp_path / f"{index}{suffix.upper() if index % 2 else suffix}").write_bytes(b"")
    (tmp_path / "notes.txt").write_bytes(b"")
    (tmp_path / "folder.png").mkdir()
    assert len(list_images(tmp_path)) == len(IMAGE_SUFFIXES)
