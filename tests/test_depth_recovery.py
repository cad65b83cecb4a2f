"""Metric depth from relative disparity (stages/lib/depth/recovery.py): the shift from the right angles of a room's
planes, the scale from the camera-height prior, and bg_depth reading a relative `disparity` sidecar through it."""
from __future__ import annotations

import json

import numpy as np
import pytest

from stages.app.pipeline import build_graph
from stages.bg_depth import run as bg_depth
from stages.contract.errors import StageError
from stages.engine.context import Context
from stages.lib.depth import formats as depth_formats
from stages.lib.depth.recovery import recover_metric_depth
from stages.lib.geometry import fov_intrinsics
from tests.factories.configs import compose_cfg
from tests.factories.media import write_image
from tests.factories.rooms import affine_disparity, room_depth


@pytest.mark.parametrize("shift", [-0.3, 0.0, 0.4])
def test_a_room_seen_through_affine_disparity_comes_back_in_metres(shift):
    """A camera 1.4 m over the floor sees a table and walls; the disparity has an unknown scale and shift. With the
    priors right (camera height, median depth), the depth comes back within 2 %, the shift within 0.02 median
    disparities."""
    depth, _, K = room_depth(camera_height=1.4)
    median = float(np.median(depth[depth > 0]))
    recovered = recover_metric_depth(affine_disparity(depth, 7.5, shift), K, 1.4, median, 20.0,
                                     np.random.default_rng(0))
    assert recovered.shift == pytest.approx(shift / (1 + shift), abs=0.02)  # in median disparities of the input
    assert recovered.shift_from.startswith("right angles of") and recovered.scale_from.startswith("camera 1.4 m")
    ratio = recovered.depth[depth > 0] / depth[depth > 0]
    assert np.all(recovered.depth[depth > 0] > 0)
    assert np.percentile(np.abs(ratio - 1), 95) < 0.02


def test_the_scale_is_the_mean_of_the_two_priors():
    """The camera is really 1.0 m high; assuming 1.4 m and a median depth of 2 m scales the room by the geometric
    mean of 1.4 / 1.0 and 2 m / its true median depth."""
    depth, _, K = room_depth(camera_height=1.0)
    recovered = recover_metric_depth(affine_disparity(depth, 1.0, 0.2), K, 1.4, 2.0, 20.0, np.random.default_rng(0))
    expected = np.sqrt(1.4 / 1.0 * 2.0 / np.median(depth[depth > 0]))
    assert np.median(recovered.depth[depth > 0] / depth[depth > 0]) == pytest.approx(expected, rel=0.03)
    assert recovered.scale_from == "camera 1.4 m above the lowest horizontal surface and median depth 2 m"


def test_a_lone_plane_does_not_tell_the_shift():
    """A wall filling the view: nothing to be at right angles with, so the shift is kept at 0 and the record says
    so; with no horizontal surface the scale comes from the median depth."""
    K = fov_intrinsics(96, 72)
    u = np.arange(96) + 0.5
    wall = np.repeat((2.0 / (1.0 + 0.3 * (u - K[0, 2]) / K[0, 0]))[None], 72, axis=0)   # a wall turned 17 degrees
    recovered = recover_metric_depth(affine_disparity(wall, 1.0, 0.3), K, 1.4, 2.0, 20.0, np.random.default_rng(0))
    assert recovered.shift == 0.0 and "do not tell it" in recovered.shift_from
    assert recovered.scale_from == "median depth 2 m (no horizontal surface below the camera)"
    assert np.median(recovered.depth[recovered.depth > 0]) == pytest.approx(2.0, rel=1e-3)


def test_a_map_without_positive_disparity_is_an_error():
    with pytest.raises(StageError, match="no positive value"):
        recover_metric_depth(np.zeros((8, 8)), fov_intrinsics(8, 8), 1.4, 2.0, 20.0, np.random.default_rng(0))


def test_a_disparity_sidecar_is_read_like_a_relative_models_output(tmp_path):
    """<stem>.depth.disparity.npy beside a photo: found, read as disparity (not metres), and turned into metres
    by the recovery, which depth.json records."""
    depth, _, K = room_depth(160, 120, camera_height=1.4)
    image = write_image(tmp_path / "room.png", np.full((120, 160, 3), 90, np.uint8))
    sidecar = tmp_path / "room.depth.disparity.npy"
    np.save(sidecar, affine_disparity(depth, 3.0, 0.25))
    assert depth_formats.find_sidecar_files(image)["depth"] == sidecar
    assert depth_formats.detect_sidecar_format(sidecar) == "disparity"
    assert depth_formats.sidecar_size(sidecar, "disparity") == (160, 120)
    out = tmp_path / "out"
    out.mkdir()
    params = {"median_depth_m": float(np.median(depth))}  # the priors right: camera 1.4 m and this median
    metrics = bg_depth.run(Context("bg_depth", "room", params, {"image": image, "depth": sidecar}, out))
    record = json.loads((out / "depth.json").read_text())
    assert record["provider"] == "sidecar" and record["sidecar_format"] == "disparity" and record["metric"] is True
    assert record["recovery"]["shift"] == pytest.approx(0.2, abs=0.02) and metrics["recovery"] == record["recovery"]
    recovered = np.load(out / "depth.npy")
    np.testing.assert_allclose(recovered[depth > 0], depth[depth > 0], rtol=0.03)


def test_the_sample_objects_compose_on_backgrounds_with_disparity_sidecars(tmp_path):
    """What +experiment=mono_depth composes on: the sample's objects and test sets, and only the photos of
    data.backgrounds (data.sample_backgrounds=false), each read with its disparity sidecar."""
    depth, _, _ = room_depth(64, 48)
    write_image(tmp_path / "kitchen.png", np.full((48, 64, 3), 90, np.uint8))
    np.save(tmp_path / "kitchen.depth.disparity.npy", affine_disparity(depth, 2.0, 0.1))
    graph = build_graph(compose_cfg([f"data.backgrounds={tmp_path}", "data.sample_backgrounds=false"]), tmp_path)
    nodes = graph.nodes["bg_depth"]
    assert [node.item for node in nodes] == ["kitchen"] and "sample" in graph.nodes
    assert nodes[0].inputs["depth"] == tmp_path / "kitchen.depth.disparity.npy" and nodes[0].params["model"] == "none"
    default = build_graph(compose_cfg([f"data.backgrounds={tmp_path}"]), tmp_path).nodes["bg_depth"]
    assert len(default) == 41  # by default the sample's 40 backgrounds and the folder's photo
