"""Tests of the train_maskrcnn stage and its detection subpackage (real training, tiny sizes)."""
import copy
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from torchvision.models.detection.roi_heads import RoIHeads

from stages.engine.context import Context
from stages.engine.settings import typed_settings
from stages.lib.detection.backbones import Lite0Body, build_backbone
from stages.lib.detection.data import (CLOSEUP_MAX_ZOOM, Augmentation, CocoInstances, augment, closeup_of_instance,
                                       crop_around_instance)
from stages.lib.detection.efficientnet_lite import (Conv2dSame, EfficientNetLite0, conv_norm, lite0_weights_path,
                                                    load_lite0_imagenet)
from stages.lib.detection.model import build_maskrcnn, load_detector
from stages.lib.detection.model_config import BACKBONES
from stages.lib.detection.model_config import model_config_of
from stages.lib.masks.dice import add_mask_dice, dice_loss
from tests.factories.shapes import write_shapes_dataset
from stages.contract.errors import StageError
from stages.train_maskrcnn.run import BatchSource, batch_stream, lr_at, run
from stages.train_maskrcnn.spec import TrainMaskrcnnConfig, for_device

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

TINY = dict(image_size=96, threads=1, lr=0.02, warmup_iterations=3, batch_size=2, rpn_post_nms_train=100,
            box_batch_size_per_image=32, scale_min=0.9, scale_max=1.1)


@pytest.fixture(scope="module")
def shapes(tmp_path_factory) -> Path:
    return write_shapes_dataset(tmp_path_factory.mktemp("shapes"), 8, size=96, seed=0)


def train(dataset: Path, out: Path, **params) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    ctx = Context("train_maskrcnn", "test", {**TINY, **params}, {"dataset": dataset}, out, seed=3)
    return run(ctx)


def test_lite0_weights_load_strictly_with_expected_feature_shapes():
    state = torch.load(lite0_weights_path(), map_location="cpu", weights_only=True)
    net = EfficientNetLite0()
    net.load_state_dict(state, strict=True)  # raises on any missing or unexpected key
    assert len(state) == 296
    features = Lite0Body(net).eval()(torch.zeros(1, 3, 96, 128))
    assert [tuple(f.shape) for f in features.values()] == [(1, 40, 12, 16), (1, 112, 6, 8), (1, 320, 3, 4)]


def test_lite0_classifies_a_real_photo(real):
    from torchvision.models import ResNet18_Weights
    net = EfficientNetLite0().eval()
    load_lite0_imagenet(net)
    image = Image.open(sorted((real / "plush_dog" / "images").glob("*.jpg"))[0]).convert("RGB").resize((224, 224))
    x = (torch.from_numpy(np.array(image)).permute(2, 0, 1).float()[None] - 127) / 128  # [1, 3, 224, 224]
    with torch.no_grad():
        top = net(x)[0].topk(3).indices
    names = [ResNet18_Weights.IMAGENET1K_V1.meta["categories"][i] for i in top]
    assert "teddy" in names, names


def test_lr_schedule_warms_up_then_decays():
    cfg = TrainMaskrcnnConfig(warmup_iterations=10, lr=0.01)
    lrs = [lr_at(cfg, i, 100) for i in range(100)]
    assert lrs[0] < 1e-4 and np.all(np.diff(lrs[:11]) > 0) and lrs[10] == pytest.approx(0.01)
    assert np.all(np.diff(lrs[10:]) < 0) and lrs[-1] > 0.05 * 0.01


def test_augmentation_keeps_masks_on_their_pixels(shapes):
    dataset = CocoInstances(shapes, 96)
    image, masks, _ = dataset.raw(0)
    rng = np.random.default_rng(0)
    for _ in range(5):
        aug_image, aug_masks = augment(torch.from_numpy(image.copy()).permute(2, 0, 1).float() / 255,
                                       torch.from_numpy(masks), rng, Augmentation(True, 0.6, 1.6, 0.0))
        for mask in aug_masks:
            if mask.any():  # shapes are flat-coloured: one colour under the whole mask
                assert aug_image[:, mask].std(dim=1).max() < 1e-6


def dataset_loss(model: torch.nn.Module, dataset: CocoInstances) -> float:
    """Summed Mask R-CNN training losses over all images, without augmentation, fixed sampling seed."""
    model.train()
    torch.manual_seed(0)
    with torch.no_grad():
        return sum(sum(model(*[[x] for x in dataset.sample(i)]).values()).item() for i in range(len(dataset)))


def test_tiny_training_lowers_loss_and_writes_outputs(shapes, tmp_path):
    metrics = train(shapes, tmp_path, epochs=4)
    record = json.loads((tmp_path / "train.json").read_text())
    losses = [c["loss"] for c in record["loss_curve"]]
    assert len(losses) == 16 and record["iterations"] == 16 and record["seconds_per_iteration"] > 0
    dataset = CocoInstances(shapes, 96)
    torch.manual_seed(3)  # the stage's seed: the same initial weights as the run
    before = dataset_loss(build_maskrcnn(model_config_of(TrainMaskrcnnConfig(**TINY)), 2), dataset)
    after = dataset_loss(load_detector(tmp_path / "model.pt")[0], dataset)
    assert after < 0.8 * before, (before, after)
    saved = torch.load(tmp_path / "model.pt", weights_only=True)
    assert saved["category_names"] == ["red_box", "blue_disc"] and saved["model_config"]["image_size"] == 96
    assert metrics["final_loss"] == pytest.approx(np.mean(losses[-10:]))


def test_finer_mask_grid_trains_and_loads_at_its_size(shapes, tmp_path):
    train(shapes, tmp_path, epochs=1, mask_roi_size=28)
    model, cfg, _ = load_detector(tmp_path / "model.pt")
    assert cfg.mask_roi_size == 28 and model.roi_heads.mask_roi_pool.output_size == (28, 28)
    pooled = torch.zeros(2, cfg.fpn_channels, 28, 28)                                   # [RoIs, C, 28, 28]
    with torch.no_grad():
        logits = model.roi_heads.mask_predictor(model.roi_heads.mask_head(pooled))
    assert logits.shape == (2, 3, 56, 56)                        # masks on a 56 x 56 grid, one per class


def test_stride4_mask_level_trains_and_loads_with_the_rpn_on_three_levels(shapes, tmp_path):
    train(shapes, tmp_path, epochs=1, mask_feature_stride=4)
    model, cfg, _ = load_detector(tmp_path / "model.pt")
    assert cfg.mask_feature_stride == 4
    model.eval()
    images = torch.rand(1, 3, 96, 96)
    features = model.backbone(images)
    assert [(name, f.shape[-1]) for name, f in features.items()] == [("fine", 24), ("0", 12), ("1", 6), ("2", 3)]
    assert model.roi_heads.mask_roi_pool.featmap_names == ["fine", "0", "1", "2"]
    assert model.roi_heads.box_roi_pool.featmap_names == ["0", "1", "2"]
    image_list = model.transform(list(images))[0]
    anchors = model.rpn.anchor_generator(image_list, list(features.values())[1:])
    with torch.no_grad():
        proposals, _ = model.rpn(image_list, features)  # the stride-4 level would need a fourth anchor size
    assert len(anchors[0]) == 3 * 2 * (12 * 12 + 6 * 6 + 3 * 3) and len(proposals) == 1
    with pytest.raises(ValueError, match="mask_feature_stride must be 4 or 8"):
        TrainMaskrcnnConfig(mask_feature_stride=2)


@pytest.mark.parametrize("name", BACKBONES)
def test_every_backbone_gives_the_stride4_level_first(name):
    backbone = build_backbone(name, frozen=False, weights=None, trainable_layers=5, fpn_channels=16, fine=True)
    with torch.no_grad():
        features = backbone.module(torch.rand(1, 3, 64, 64))
    assert [(level, tuple(f.shape[1:])) for level, f in features.items()] == [
        ("fine", (16, 16, 16)), ("0", (16, 8, 8)), ("1", (16, 4, 4)), ("2", (16, 2, 2))]


def test_checkpoint_resumes_with_the_same_state(shapes, tmp_path):
    straight = tmp_path / "straight"
    train(shapes, straight, epochs=1)
    checkpoints = tmp_path / "checkpoints"
    train(shapes, tmp_path / "first", epochs=1, checkpoint_every=2, checkpoint_dir=str(checkpoints))
    assert torch.load(checkpoints / "last.pt", weights_only=True)["iteration"] == 2
    train(shapes, tmp_path / "resumed", epochs=1, checkpoint_every=2, checkpoint_dir=str(checkpoints))
    record = json.loads((tmp_path / "resumed" / "train.json").read_text())
    assert record["resumed_from"] == 2 and [c["iteration"] for c in record["loss_curve"]] == [0, 1, 2, 3]
    expected = torch.load(straight / "model.pt", weights_only=True)["state_dict"]
    resumed = torch.load(tmp_path / "resumed" / "model.pt", weights_only=True)["state_dict"]
    for key, value in expected.items():
        torch.testing.assert_close(resumed[key], value, msg=key)


def test_missing_annotations_is_a_clear_error(tmp_path):
    (tmp_path / "data" / "images").mkdir(parents=True)
    with pytest.raises(StageError, match="annotations.json"):
        train(tmp_path / "data", tmp_path / "out", epochs=0.25)


def test_resnet_without_a_weights_file_is_a_clear_error(shapes, tmp_path):
    with pytest.raises(StageError, match="weights_path"):
        train(shapes, tmp_path, epochs=0.25, backbone="resnet18_fpn", pretrained=True)


def test_crop_keeps_an_instance_at_full_scale():
    image = torch.rand(3, 60, 100)
    masks = torch.zeros(2, 60, 100, dtype=torch.bool)
    masks[0, 40:50, 80:95] = True
    masks[1, 5:15, 5:12] = True
    rng = np.random.default_rng(0)
    for _ in range(20):
        crop_image, crop_masks = crop_around_instance(image, masks, 32, rng)
        assert crop_image.shape == (3, 32, 32) and crop_masks.shape == (2, 32, 32)
        assert crop_masks.flatten(1).any(1).any()  # the chosen instance's centre is inside
        assert crop_masks.sum() <= masks.sum()
    whole_image, whole_masks = crop_around_instance(image, masks, 128, rng)
    assert whole_image is image and whole_masks is masks


def box_sides(mask: torch.Tensor) -> tuple[int, int, int, int, int, int]:
    """(height, width, top, left, bottom gap, right gap) of a mask's box."""
    ys, xs = torch.nonzero(mask, as_tuple=True)
    return (int(ys.max() - ys.min()) + 1, int(xs.max() - xs.min()) + 1, int(ys.min()), int(xs.min()),
            mask.shape[0] - int(ys.max()) - 1, mask.shape[1] - int(xs.max()) - 1)


def test_closeup_shows_one_instance_whole_at_the_chosen_fill():
    image = torch.rand(3, 120, 160)
    masks = torch.zeros(1, 120, 160, dtype=torch.bool)
    masks[0, 30:90, 50:80] = True  # 60 x 30 px
    rng = np.random.default_rng(0)
    for fill in (0.5, 0.8, 1.0):
        for _ in range(5):
            window, window_masks = closeup_of_instance(image, masks, 64, fill, rng)
            assert window.shape == (3, 64, 64) and window_masks.shape == (1, 64, 64)
            height, width, *gaps = box_sides(window_masks[0])
            assert abs(height - fill * 64) <= 2 and abs(width - fill * 32) <= 2  # zoomed, aspect kept
            assert min(gaps) >= 0 and (fill == 1.0 or max(gaps) > 0)  # whole, inside the window


def test_closeup_of_a_small_instance_is_capped_and_an_empty_image_gets_a_plain_window():
    image = torch.rand(3, 200, 200)
    masks = torch.zeros(1, 200, 200, dtype=torch.bool)
    masks[0, 100:110, 100:105] = True  # 10 px tall
    window, window_masks = closeup_of_instance(image, masks, 128, 1.0, np.random.default_rng(1))
    assert box_sides(window_masks[0])[0] <= 10 * CLOSEUP_MAX_ZOOM + 1
    empty = torch.zeros(0, 200, 200, dtype=torch.bool)
    window, window_masks = closeup_of_instance(image, empty, 128, 1.0, np.random.default_rng(1))
    assert window.shape == (3, 128, 128) and window_masks.shape == (0, 128, 128)


@pytest.mark.parametrize("bad", [{"closeup_share": 1.5}, {"closeup_fill": [0.5, 1.2]}, {"closeup_fill": [0.8, 0.5]},
                                 {"closeup_fill": [0.0, 1.0]}])
def test_closeup_settings_out_of_range_fail_at_start(bad):
    """The check every node's settings get at start (Node.settings)."""
    with pytest.raises(StageError, match="closeup"):
        typed_settings(TrainMaskrcnnConfig, "train_maskrcnn",
                       for_device({**asdict(TrainMaskrcnnConfig()), **bad}, "cpu"))


def test_closeups_are_part_of_the_training_batches(shapes):
    cfg = TrainMaskrcnnConfig(**{**TINY, "train_crop": 64, "closeup_share": 1.0, "closeup_fill": [0.9, 0.9]})
    for image, target in BatchSource(CocoInstances(shapes, 96), cfg, seed=5)[0]:
        boxes = target["boxes"]
        assert image.shape[-2:] == (64, 64)
        sides = torch.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
        assert (sides - 0.9 * 64).abs().min() <= 2  # one instance fills 90 % of the window


def test_loader_workers_give_the_same_batches(shapes):
    cfg = TrainMaskrcnnConfig(**{**TINY, "train_crop": 64})
    source = BatchSource(CocoInstances(shapes, 96), cfg, seed=5)
    inline = list(batch_stream(source, range(2, 5), workers=0))
    ahead = list(batch_stream(source, range(2, 5), workers=1))
    assert len(inline) == len(ahead) == 3
    for batch_a, batch_b in zip(inline, ahead):
        for (image_a, target_a), (image_b, target_b) in zip(batch_a, batch_b):
            assert max(image_a.shape[-2:]) <= 64
            torch.testing.assert_close(image_a, image_b)
            torch.testing.assert_close(target_a["boxes"], target_b["boxes"])


def test_same_padding_fast_path_matches_explicit_padding():
    torch.manual_seed(0)
    for kernel, stride, groups in ((1, 1, 1), (3, 1, 8), (5, 1, 8), (3, 2, 8), (5, 2, 1)):
        conv = Conv2dSame(8, 8, kernel, stride=stride, groups=groups)
        x = torch.randn(1, 8, 13, 10)
        pads = []
        for size in (x.shape[-1], x.shape[-2]):
            total = max((-(-size // stride) - 1) * stride + kernel - size, 0)
            pads += [total // 2, total - total // 2]
        expected = torch.nn.functional.conv2d(torch.nn.functional.pad(x, pads), conv.weight, None, stride, 0, 1, groups)
        torch.testing.assert_close(conv(x), expected)


def test_cuda_budget_applies_only_on_a_gpu():
    params = asdict(TrainMaskrcnnConfig())
    on_cpu, on_gpu = for_device(params, "cpu"), for_device(params, "cuda")
    assert "cuda" not in on_cpu and "cuda" not in on_gpu
    assert on_cpu["image_size"] == params["image_size"] and on_cpu["epochs"] == params["epochs"]
    assert {k: on_gpu[k] for k in params["cuda"]} == params["cuda"] and on_gpu != on_cpu
    TrainMaskrcnnConfig(**on_gpu)  # every key is a setting
    with pytest.raises(ValueError, match="imag_size"):
        for_device({**params, "cuda": {"imag_size": 640}}, "cpu")


def test_frozen_norm_folded_into_the_convolution_keeps_values_and_gradients():
    from torchvision.ops.misc import FrozenBatchNorm2d
    torch.manual_seed(0)
    conv, norm = Conv2dSame(6, 4, 3, stride=2), FrozenBatchNorm2d(4, eps=1e-3)
    norm.weight.copy_(torch.rand(4) + 0.5)
    norm.bias.copy_(torch.randn(4))
    norm.running_mean.copy_(torch.randn(4))
    norm.running_var.copy_(torch.rand(4) + 0.1)
    x = torch.randn(2, 6, 11, 9)
    folded = conv_norm(conv, norm, x)
    (folded ** 2).sum().backward()
    grad_folded = conv.weight.grad.clone()
    conv.weight.grad = None
    reference = norm(conv(x))
    (reference ** 2).sum().backward()
    torch.testing.assert_close(folded, reference, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(grad_folded, conv.weight.grad, rtol=1e-4, atol=1e-4)


def test_bf16_autocast_trains(shapes, tmp_path):
    metrics = train(shapes, tmp_path, epochs=1, bf16=True)
    assert np.isfinite(metrics["final_loss"])
    state = torch.load(tmp_path / "model.pt", weights_only=True)["state_dict"]
    assert all(v.dtype != torch.bfloat16 for v in state.values())  # the weights stay float32


def test_dice_loss_scores_the_overlap_of_each_mask():
    target = torch.zeros(2, 8, 8)
    target[:, 2:6, 2:6] = 1.0                                                             # [masks, M, M]
    assert dice_loss(target, target).item() == pytest.approx(0.0, abs=0.02)             # 1 / 33 from the +1
    assert dice_loss(1.0 - target, target).item() == pytest.approx(1.0, abs=0.02)       # disjoint
    half = target.clone()
    half[:, 2:4] = 0.0                                                                   # half of each mask found
    assert dice_loss(half, target).item() == pytest.approx(1 - 17 / 25, abs=1e-6)       # (2*8+1) / (8+16+1)


def test_the_dice_term_joins_the_training_losses_and_leaves_the_rest_as_it_was(shapes):
    dataset = CocoInstances(shapes, 96)
    cfg = model_config_of(TrainMaskrcnnConfig(**TINY))
    torch.manual_seed(3)
    plain_model = build_maskrcnn(cfg, 2).train()
    weighted = {}
    for weight in (1.0, 2.5):
        model = copy.deepcopy(plain_model)
        add_mask_dice(model, weight)
        assert model.state_dict().keys() == plain_model.state_dict().keys()
        torch.manual_seed(0)
        weighted[weight] = model(*[[x] for x in dataset.sample(0)])
    torch.manual_seed(0)
    plain = plain_model(*[[x] for x in dataset.sample(0)])
    assert "loss_mask_dice" not in plain and add_mask_dice(plain_model, 0.0).roi_heads.__class__ is RoIHeads
    assert weighted[1.0]["loss_mask"].item() == pytest.approx(plain["loss_mask"].item(), rel=1e-6)
    assert 0.05 < weighted[1.0]["loss_mask_dice"].item() < 1.0                           # unsure masks at the start
    assert weighted[2.5]["loss_mask_dice"].item() == pytest.approx(2.5 * weighted[1.0]["loss_mask_dice"].item(), rel=1e-5)
    with_grad = copy.deepcopy(plain_model)
    add_mask_dice(with_grad, 1.0)
    torch.manual_seed(0)
    with_grad(*[[x] for x in dataset.sample(0)])["loss_mask_dice"].backward()
    assert with_grad.roi_heads.mask_predictor.mask_fcn_logits.weight.grad.abs().sum() > 0
    with_grad.eval(), plain_model.eval()
    with torch.no_grad():
        image = dataset.sample(0)[0]
        assert torch.equal(with_grad([image])[0]["masks"], plain_model([image])[0]["masks"])  # inference unchanged


def test_a_run_with_the_dice_term_records_it(shapes, tmp_path):
    train(shapes, tmp_path, epochs=1, mask_dice_weight=1.0)
    record = json.loads((tmp_path / "train.json").read_text())
    assert all(c["loss_mask_dice"] > 0 for c in record["loss_curve"])
    with pytest.raises(ValueError, match="mask_dice_weight"):
        TrainMaskrcnnConfig(mask_dice_weight=-1.0)
