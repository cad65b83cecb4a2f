"""The README's picture: composed training images with their instance masks, above a detector's predictions on
test photos, from one run's cache entries, as one labelled JPEG.

    python -m benchmarks.readme_figure --compose outputs/cache/compose/<key> --eval outputs/cache/eval/<key> \
        --out docs/images/overview.jpg [--rows 2] [--width 1280] [--max-kb 250]

The compose entry gives its preview.png (a grid of composed images, each mask outlined in its class colour), of
which the first `--rows` rows are kept; the eval entry gives its predictions.png (test photos with the detections
drawn). Each panel gets a caption bar naming the stage, the variant and the test set (from the entries'
manifest.json). The JPEG's quality steps down until the file is under `--max-kb`.
"""
from __future__ import annotations

import argparse
import io
import json
import math
from pathlib import Path

from PIL import Image, ImageDraw, ImageFont

PREVIEW_TILE_WIDTH = 320  # stages/lib/composition/preview.py: preview_grid's tile width
BAR_COLOUR, TEXT_COLOUR = (32, 32, 32), (255, 255, 255)


def _manifest(entry: Path) -> dict:
    path = entry / "manifest.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def composed_rows(entry: Path, rows: int) -> Image.Image:
    """The first `rows` rows of the compose entry's preview.png (its tiles' height from annotations.json)."""
    preview = Image.open(entry / "preview.png").convert("RGB")
    columns = max(1, preview.width // PREVIEW_TILE_WIDTH)
    tile_height = preview.height
    annotations = entry / "annotations.json"
    if annotations.is_file():
        images = json.loads(annotations.read_text()).get("images", [])
        if images:
            tile_height = round(PREVIEW_TILE_WIDTH * images[0]["height"] / images[0]["width"])
            tile_height = min(tile_height, preview.height // max(1, math.ceil(min(len(images), 16) / columns)))
    return preview.crop((0, 0, preview.width, min(preview.height, rows * tile_height)))


def captioned(panel: Image.Image, text: str, width: int) -> Image.Image:
    """`panel` scaled to `width` under a dark bar holding `text`."""
    panel = panel.resize((width, round(panel.height * width / panel.width)), Image.Resampling.LANCZOS)
    font = ImageFont.load_default(size=max(12, width // 56))
    bar = round(font.size * 1.8)
    out = Image.new("RGB", (width, bar + panel.height), BAR_COLOUR)
    ImageDraw.Draw(out).text((font.size // 2, (bar - font.size) // 2), text, fill=TEXT_COLOUR, font=font)
    out.paste(panel, (0, bar))
    return out


def figure(compose: Path, evaluation: Path, rows: int = 2, width: int = 1280) -> Image.Image:
    """The two captioned panels stacked."""
    compose_item = _manifest(compose).get("item", "")
    eval_item = _manifest(evaluation).get("item", "")
    variant, _, test_set = eval_item.partition("@")
    panels = [
        captioned(composed_rows(compose, rows), f"Composed training images, instance masks outlined"
                  f"{f' (compose, variant {compose_item})' if compose_item else ''}", width),
        captioned(Image.open(evaluation / "predictions.png").convert("RGB"),
                  f"The trained detector's predictions on test photos"
                  f"{f' ({test_set}, variant {variant})' if test_set else ''}", width),
    ]
    out = Image.new("RGB", (width, sum(p.height for p in panels)), (255, 255, 255))
    top = 0
    for panel in panels:
        out.paste(panel, (0, top))
        top += panel.height
    return out


def save_jpeg(image: Image.Image, out: Path, max_kb: float) -> int:
    """Write `image` as the best-quality JPEG under `max_kb` (quality 90 down to 40); its quality."""
    for quality in range(90, 35, -5):
        buffer = io.BytesIO()
        image.save(buffer, "JPEG", quality=quality, optimize=True, progressive=True)
        if buffer.tell() <= max_kb * 1024 or quality == 40:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(buffer.getvalue())
            return quality
    raise AssertionError("unreachable")


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.readme_figure", description=__doc__.split("\n\n")[0])
    parser.add_argument("--compose", type=Path, required=True, help="a compose cache entry (holds preview.png)")
    parser.add_argument("--eval", type=Path, required=True, help="an eval cache entry (holds predictions.png)")
    parser.add_argument("--out", type=Path, default=Path("docs/images/overview.jpg"))
    parser.add_argument("--rows", type=int, default=2, help="rows of the compose preview to keep")
    parser.add_argument("--width", type=int, default=1280, help="width of the figure in pixels")
    parser.add_argument("--max-kb", type=float, default=250.0)
    args = parser.parse_args()
    image = figure(args.compose, args.eval, args.rows, args.width)
    quality = save_jpeg(image, args.out, args.max_kb)
    size = args.out.stat().st_size / 1024
    print(f"{args.out}: {image.width}x{image.height}, JPEG quality {quality}, {size:.0f} KB")
    if size > args.max_kb:
        raise SystemExit(f"{args.out} is {size:.0f} KB, over --max-kb {args.max_kb:.0f} at quality 40")


if __name__ == "__main__":
    main()
