"""The sample's ground truth as the extract benchmark scores against it: the support under the object (a rug's
top, not the floor under it) and the pixels where clutter hides the object."""
import cv2
import numpy as np
import pytest

from benchmarks.lib.truth_views import TruthViews, support_top, supported_truth, visible_iou
from stages.lib.gaussians.model import Gaussians
from stages.lib.geometry import fov_intrinsics, look_at_viewmat
from stages.lib.sample_scene.capture import CAPTURE_HFOV_DEG
from stages.lib.sample_scene.objects import build_object
from stages.records.capture_truth import CaptureTruth


def capture_truth(name: str, seed: int, width: int = 640, height: int = 480, viewmats=None) -> CaptureTruth:
    """The gt.json the sample writes for (name, seed) at width x height, without its frames unless given."""
    return CaptureTruth(name, 0.09, fov_intrinsics(width, height, CAPTURE_HFOV_DEG), width, height, 10.0,
                        viewmats or {}, np.array([0.0, 0.0, 1.0]), np.zeros(3), seed=seed)


def test_support_is_the_top_of_the_rug_under_the_object_and_the_floor_elsewhere():
    # seeds 4 and 6 stand the sample's eyedrops on an 8 mm rug; seed 5 on the bare floor
    assert abs(support_top(capture_truth("eyedrops", 4)) - 0.008) < 1e-6
    assert abs(support_top(capture_truth("eyedrops", 6)) - 0.008) < 1e-6
    assert abs(support_top(capture_truth("eyedrops", 5))) < 1e-6
    lifted, rise = supported_truth(capture_truth("eyedrops", 4))
    assert rise > 0.007 and np.allclose(lifted.ground_point, [0.0, 0.0, rise])


def test_pixels_hidden_by_clutter_are_left_out_and_the_outline_is_not(tmp_path):
    viewmat = look_at_viewmat(np.array([0.15, 0.03, 0.08]), np.array([0.0, 0.0, 0.045]))
    gt = capture_truth("eyedrops", 5, 160, 120, {0: viewmat})
    truth = TruthViews(gt, tmp_path, build_object("eyedrops", 0.09, 5))
    silhouette = truth.silhouette(0)  # [H, W] the object alone
    assert 0.05 < silhouette.mean() < 0.6
    rows = np.flatnonzero(silhouette.any(axis=1))
    visible = silhouette.copy()
    visible[rows[len(rows) // 2]:] = False  # clutter in front of the lower half
    outline = silhouette & ~(cv2.erode(silhouette.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
    visible[np.nonzero(outline)[0][::3], np.nonzero(outline)[1][::3]] = False  # the outline sampled apart
    (tmp_path / "masks").mkdir()
    cv2.imwrite(str(tmp_path / "masks" / "0000.png"), visible.astype(np.uint8) * 255)
    read_visible, hidden = truth.masks(0)
    assert np.array_equal(read_visible, visible)
    lower = np.zeros_like(silhouette)
    lower[rows[len(rows) // 2] + 1:] = True
    assert hidden[lower & silhouette].mean() > 0.9  # the hidden half is left out ...
    assert not hidden[: rows[len(rows) // 2] - 1].any()  # ... and the one-pixel outline above it is not
    predicted = silhouette  # a perfect cut, rendered alone
    assert visible_iou(predicted, visible, hidden) > 0.95
    assert visible_iou(predicted, visible, np.zeros_like(hidden)) < 0.7


def test_a_view_showing_under_a_tenth_of_the_object_is_not_scored(tmp_path):
    viewmat = look_at_viewmat(np.array([0.15, 0.03, 0.08]), np.array([0.0, 0.0, 0.045]))
    gt = capture_truth("eyedrops", 5, 160, 120, {0: viewmat, 1: viewmat, 2: viewmat})
    truth = TruthViews(gt, tmp_path, build_object("eyedrops", 0.09, 5))
    silhouette = truth.silhouette(0)  # [H, W]
    rows = np.flatnonzero(silhouette.any(axis=1))
    (tmp_path / "masks").mkdir()
    for index, shown in enumerate((1.0, 0.3, 0.05)):  # clutter hides all but the top `shown` of the rows
        visible = silhouette.copy()
        visible[rows[0] + int(round(shown * len(rows))):] = False
        cv2.imwrite(str(tmp_path / "masks" / f"{index:04d}.png"), visible.astype(np.uint8) * 255)
    shares = [truth.visible_share(index) for index in range(3)]
    assert shares[0] == 1.0 and 0.15 < shares[1] < 0.5 and shares[2] < 0.1
    assert truth.scored_views([0, 1, 2]) == ([0, 1], [2])


@pytest.mark.parametrize("height, expected", [(-0.004, 1.0), (0.004, 0.0)])
def test_missed_pixels_drawn_by_gaussians_under_the_support_are_counted(tmp_path, height, expected):
    from benchmarks.lib.cut_scoring import missed_share_under_support
    grid = np.stack(np.meshgrid(np.linspace(-0.05, 0.05, 21), np.linspace(-0.05, 0.05, 21)), -1).reshape(-1, 2)
    patch = Gaussians.from_points(np.c_[grid, np.full(len(grid), height)], np.full((len(grid), 3), 0.5))  # [441]
    viewmat = look_at_viewmat(np.array([0.0, -0.05, 0.3]), np.zeros(3))
    gt = capture_truth("eyedrops", 5, 64, 48, {0: viewmat})
    truth = TruthViews(gt, tmp_path, [])  # no object silhouette: nothing hidden
    visible = np.zeros((48, 64), bool)
    visible[20:28, 28:36] = True  # the true object: pixels in the middle of the patch, which the cut misses
    (tmp_path / "masks").mkdir()
    cv2.imwrite(str(tmp_path / "masks" / "0000.png"), visible.astype(np.uint8) * 255)
    under = patch.means[:, 2].numpy() < 0
    share = missed_share_under_support(patch, under, truth, 0, predicted=np.zeros_like(visible))
    assert share == pytest.approx(expected, abs=1e-6)


def test_gaussians_in_a_vases_cavity_are_object_and_those_beside_it_or_among_leaves_are_not():
    """A vase's cavity shows only the vase's inside through its mouth: Gaussians there are object (`cavity`); one
    beside the vase, above its mouth or on the plant's axis among its leaves is not enclosed."""
    from benchmarks.lib.cut_scoring import enclosed_sideways, object_membership
    from stages.lib.sample_scene.meshes import sample_surface
    up = np.array([0.0, 0.0, 1.0])
    vase = build_object("vase", 0.22, 5)
    points = np.array([[0.0, 0.0, 0.18], [0.0, 0.0, 0.21], [0.11, -0.02, 0.08], [0.0, 0.0, 0.24]])  # [4, 3]
    assert enclosed_sideways(vase, points, up).tolist() == [True, True, False, False]
    plant = build_object("plant", 0.3, 5)
    assert not enclosed_sideways(plant, np.array([[0.0, 0.0, 0.2]]), up).any()
    gt = capture_truth("vase", 5)
    surface = sample_surface(vase, 20000, np.random.default_rng(0))  # [20000, 3]
    membership = object_membership(points, gt, surface, vase, 0.01)
    assert membership["cavity"].tolist() == [True, True, False, False]
    assert membership["is_object"].tolist() == [True, True, False, False]
