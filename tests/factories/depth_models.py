"""Depth Anything models built offline for tests: the architecture of the published checkpoints (transformers'
DepthAnythingConfig with a Dinov2Config backbone, DepthAnythingForDepthEstimation), tiny and randomly initialised,
saved with save_pretrained into a folder or into a Hugging Face cache laid out as hf download leaves it
(models--<org>--<name>/snapshots/<revision>/ and refs/main). Nothing is downloaded."""
from __future__ import annotations

from pathlib import Path

from stages.lib.depth.models import HubModel


def tiny_config(kind: str = "metric", **backbone):
    """A DepthAnythingConfig of the published layout at toy size: 4 transformer layers of width 32, the neck and
    head narrowed to match; `kind` "metric" (max depth 20 m, like the indoor checkpoint) or "relative"."""
    from transformers import DepthAnythingConfig, Dinov2Config

    dinov2 = Dinov2Config(image_size=56, patch_size=14, hidden_size=32, num_hidden_layers=4, num_attention_heads=2,
                          intermediate_size=64, out_indices=[1, 2, 3, 4], reshape_hidden_states=False,
                          apply_layernorm=True, **backbone)
    return DepthAnythingConfig(backbone_config=dinov2, reassemble_hidden_size=32, neck_hidden_sizes=[8, 16, 16, 32],
                               fusion_hidden_size=16, head_hidden_size=8, depth_estimation_type=kind,
                               max_depth=20 if kind == "metric" else 1)


def full_size_config(kind: str = "metric"):
    """The configuration of Depth-Anything-V2-Small and its metric fine-tunes (24.8 M parameters)."""
    from transformers import DepthAnythingConfig, Dinov2Config

    dinov2 = Dinov2Config(image_size=518, patch_size=14, hidden_size=384, num_hidden_layers=12, num_attention_heads=6,
                          out_indices=[3, 6, 9, 12], reshape_hidden_states=False, apply_layernorm=True)
    return DepthAnythingConfig(backbone_config=dinov2, depth_estimation_type=kind,
                               max_depth=20 if kind == "metric" else 1)


def save_model(folder: Path, config, seed: int = 0) -> Path:
    """A randomly initialised DepthAnythingForDepthEstimation of `config` saved into `folder` (save_pretrained:
    config.json + model.safetensors), the bias of its last layer set to 1 so that its map is positive, as a
    trained model's is; returns the folder."""
    import torch
    from transformers import DepthAnythingForDepthEstimation

    torch.manual_seed(seed)
    model = DepthAnythingForDepthEstimation(config)
    with torch.no_grad():
        model.head.conv3.bias.fill_(1.0)
    model.save_pretrained(folder)
    return Path(folder)


def fake_hub_cache(cache: Path, model: HubModel, kind: str = "metric") -> Path:
    """A tiny model saved as the snapshot of `model` in a Hugging Face cache folder `cache` (what HF_HUB_CACHE
    points at); returns the snapshot folder."""
    repo = cache / model.folder_name()
    snapshot = save_model(repo / "snapshots" / model.revision, tiny_config(kind))
    (repo / "refs").mkdir(parents=True, exist_ok=True)
    (repo / "refs" / "main").write_text(model.revision)
    return snapshot
