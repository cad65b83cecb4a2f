"""The model card of a model folder (MODEL_CARD.md): what the detector finds, what it was trained on, how it scored,
how its masks are made, and which versions and command made it."""
from __future__ import annotations

import platform
from importlib import metadata

PACKAGES = ("cut-and-splat", "torch", "torchvision", "onnx", "onnxruntime", "numpy", "opencv-python-headless")


def versions() -> dict[str, str]:
    """The versions of Python and of the packages the detector runs with ("not installed" for one that is not)."""
    found = {"python": platform.python_version()}
    for package in PACKAGES:
        try:
            found[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            found[package] = "not installed"
    return found


def _ap(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.1f}"


def check_text(check: dict | None) -> str:
    """export.check_onnx's comparison in words."""
    if check is None:
        return "not compared (no test photo at export)"
    text = (f"{check['detections']} / {check['reference_detections']} detections on a test photo, labels "
            f"{'equal' if check['same_labels'] else 'different'}")
    if check["max_box_difference_px"] is not None:
        text += f", boxes within {check['max_box_difference_px']:.3g} px, mask IoU at least {check['min_mask_iou']:.4f}"
    return text


def render_card(description: dict) -> str:
    """Markdown of a model folder's model.json (model_folder.write_model_folder): its class names, input and
    post-processing, and its card's facts: training {"images", "variant", "generator", "seed", "backbone",
    "iterations", "epochs", "seconds", "device"}, evaluation {test set: {"images", "box_AP", "box_AP50", "mask_AP",
    "mask_AP50"}} (empty when eval has not run), onnx_check (export.check_onnx), versions, source {"command",
    "train_maskrcnn", "created"}."""
    card, training = description["card"], description["card"]["training"]
    post = description["post_processing"]
    lines = [f"# Cut-and-Splat detector: {training['variant']}", "",
             f"Finds {len(description['class_names'])} classes: {', '.join(description['class_names'])}. Mask R-CNN "
             f"with the {training['backbone']} backbone; photos of any size (resized inside to "
             f"{description['input']['image_size']} px on the longer side).", "",
             "## Training data", "",
             f"{training['images']} images composed by `{training['generator']}` (variant `{training['variant']}`), "
             f"seed {training['seed']}; {training['iterations']} iterations ({training['epochs']} epochs) in "
             f"{training['seconds']:.0f} s on {training['device']}.", "", "## Evaluation", ""]
    if card["evaluation"]:
        lines += ["| test set | images | box AP | box AP50 | mask AP | mask AP50 |", "|---|---|---|---|---|---|"]
        lines += [f"| {name} | {m['images']} | {_ap(m['box_AP'])} | {_ap(m['box_AP50'])} | {_ap(m['mask_AP'])} | "
                  f"{_ap(m['mask_AP50'])} |" for name, m in card["evaluation"].items()]
    else:
        lines.append("Not evaluated: no eval of this detector was in the cache when it was exported.")
    lines += ["", "## Post-processing (eval's settings)", "",
              f"Masks above {post['mask_threshold']}, guided-filtered by the photo's colours (radius "
              f"{post['mask_refine_radius']} px at the detector's input size, eps {post['mask_refine_eps']}; 0 = off), "
              f"disjoint across classes from box score {post['mask_owner_score']} (None = overlaps kept); masks ranked "
              f"by `{post['mask_score']}`."]
    lines += ["", "## ONNX", "", f"model.onnx against PyTorch: {check_text(card.get('onnx_check'))}."]
    lines += ["", "## Versions", "", ", ".join(f"{name} {version}" for name, version in card["versions"].items()),
              "", "## Source", "", f"`{card['source']['command']}`, from the cache entry "
              f"`{card['source']['train_maskrcnn']}`, exported {card['source']['created']}.", ""]
    return "\n".join(lines)
