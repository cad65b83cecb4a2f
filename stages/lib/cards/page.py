"""A dataset card as a Markdown page with its figures (stages/lib/cards/stats.py's numbers and checks,
stages/lib/cards/figures.py's pictures): written into a composed dataset's folder by compose and cut_and_paste, and for
any COCO folder by `python -m stages.app.dataset_card`."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from stages.lib.cards.figures import write_examples, write_histograms
from stages.lib.cards.stats import DatasetStats, dataset_checks, dataset_stats, record_disagreements
from stages.records.coco_dataset import CocoDataset
from stages.records.placements import PlacementsRecord

CARD = "card.md"
HISTOGRAMS = "card_histograms.png"
EXAMPLES = "card_examples.jpg"


@dataclass
class Card:
    """A written card: its page, and the checks' findings (empty: nothing wrong)."""

    path: Path
    checks: list[str]


def _class_table(stats: DatasetStats, compare: DatasetStats | None) -> list[str]:
    """Markdown rows of the per-class counts (with the test set's beside them)."""
    head = "| class | instances | images | share |" + (" test instances | test share |" if compare else "")
    rows = [head, "|---" * (6 if compare else 4) + "|"]
    other = {c.name: c for c in compare.classes} if compare else {}
    for c in stats.classes:
        row = f"| {c.name} | {c.instances} | {c.images} | {c.share:.1%} |"
        if compare:
            mine = other.get(c.name)
            row += f" {mine.instances} | {mine.share:.1%} |" if mine else " - | - |"
        rows.append(row)
    return rows


def _usage_lines(generator: dict) -> list[str]:
    """Markdown lines on the photos and objects a generator used and left out (its stats.json)."""
    lines = [f"- photos: {generator.get('photos', '?')}"]
    for photo, why in sorted((generator.get("photos_without_plane") or {}).items()):
        expected = " (expected: a view without a floor)" if photo in generator.get("expected_without_plane", []) else ""
        lines.append(f"  - left out: {photo}: {why}{expected}")
    for what, items in sorted((generator.get("left_out") or {}).items()):
        for item in items if isinstance(items, list) else [items]:
            lines.append(f"- left out ({what}): {item}")
    return lines


def write_card(folder: Path, out: Path | None = None, compare: Path | None = None, samples: int = 12,
               seed: int = 0, title: str = "") -> Card:
    """Write card.md and its figures for the COCO dataset in `folder` into `out` (default: the folder itself);
    `compare`: a test set whose histograms are drawn beside the dataset's. The generator's stats.json and
    placements.json, when the folder has them, add what it used and left out and the record check. `title`: the
    card's name for the dataset, written in place of the folder's path (a stage writes into a temporary folder)."""
    folder = Path(folder)
    out = Path(out) if out is not None else folder
    out.mkdir(parents=True, exist_ok=True)
    dataset = CocoDataset.read(folder)
    stats = dataset_stats(dataset)
    record = PlacementsRecord.read(folder)
    checks = dataset_checks(stats, record_disagreements(dataset, record) if record is not None else [])
    compared = dataset_stats(CocoDataset.read(compare)) if compare is not None else None
    write_histograms(out / HISTOGRAMS, stats, compared, ("dataset", f"test set {Path(compare).name}" if compare
                                                         else "test set"))
    examples = write_examples(out / EXAMPLES, folder, dataset, samples, seed)
    generator = json.loads((folder / "stats.json").read_text()) if (folder / "stats.json").is_file() else {}
    total = max(stats.images, 1)
    lines = [f"# Dataset card: {title or folder.name}", "",
             ("" if title else f"`{folder}`: ") + f"{stats.images} images, {stats.instances} instances, "
             f"{stats.instances / total:.2f} per image" + (f"; beside the test set `{compare}`" if compare else "") + ".",
             "", "## Checks", ""]
    lines += [f"- {line}" for line in checks] or ["- none failed: every class has at least a third of the mean share, "
                                                  "every mask lies in its image, every image has an instance"
                                                  + (", and the annotations match the generator's record"
                                                     if record is not None else "")]
    lines += ["", "## Classes", "", *_class_table(stats, compared), "",
              "## Distributions", "", f"![histograms]({HISTOGRAMS})", "",
              "| instances per image | images |", "|---|---|",
              *[f"| {k} | {v} |" for k, v in sorted(stats.objects_per_image.items())], ""]
    if stats.placement:
        lines += ["| placement | instances |", "|---|---|",
                  *[f"| {kind} | {n} |" for kind, n in sorted(stats.placement.items())], ""]
    if generator:
        lines += ["## What was used", "", *_usage_lines(generator), ""]
    lines += ["## Examples", "", f"{len(examples)} images drawn at random (seed {seed}): every instance outlined, "
              "boxed and named in its class colour.", "", f"![examples]({EXAMPLES})", ""]
    (out / CARD).write_text("\n".join(lines))
    return Card(out / CARD, checks)
