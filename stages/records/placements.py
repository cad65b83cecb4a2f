"""A composed dataset's `placements.json`: what the generator placed in each image and kept (compose writes it
beside annotations.json; the dataset card compares the annotations with it, stages/lib/cards/stats.py)."""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from stages.contract.errors import StageError
from stages.records.files import read_json, write_json


@dataclass
class PlacementsRecord:
    """Per image file name, the objects placed in it: [{"object": name, "kept": bool, "why": reason or ""}]. An
    object is kept when enough of it stays visible; a kept object must have an annotation."""

    images: dict[str, list[dict]]

    JSON: ClassVar[str] = "placements.json"

    def write(self, folder: Path) -> None:
        """Write placements.json into `folder`."""
        write_json(Path(folder) / self.JSON, {"images": self.images})

    @classmethod
    def read(cls, folder: Path) -> "PlacementsRecord | None":
        """The record of a dataset folder, or None when it has none (a test set, a dataset of another tool).
        StageError naming the file when it is malformed."""
        path = Path(folder) / cls.JSON
        if not path.is_file():
            return None
        info = read_json(path, "compose")
        try:
            images = {str(name): [{"object": str(o["object"]), "kept": bool(o["kept"]), "why": str(o.get("why", ""))}
                                  for o in objects] for name, objects in info["images"].items()}
        except (KeyError, TypeError, AttributeError) as error:
            raise StageError(f"{path}: malformed ({error!r}); expected a compose output folder") from error
        return cls(images)

    def kept_by_image(self) -> dict[str, Counter]:
        """{image file name: Counter of the names of the objects kept in it}."""
        return {name: Counter(o["object"] for o in objects if o["kept"]) for name, objects in self.images.items()}
