"""frames' output `frames.json`: the selected frames in order, with where each came from.

docs/stage_contracts.md, section frames (the images themselves are `images/%04d.jpg` beside it).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from stages.contract.errors import StageError
from stages.records.files import MALFORMED, read_json, write_json


@dataclass
class FrameEntry:
    """One selected frame."""

    file: str  # relative to the frames folder, e.g. "images/0000.jpg"
    source_index: int  # frame number in the video (or image number in the folder)
    time_s: float | None  # time in the video (None for a folder of images)
    sharpness: float  # variance of the Laplacian
    source: str  # the video or image file it came from
    scale: float  # frame pixels per source pixel


@dataclass
class FramesRecord:
    """The frames a capture gave, in frame order."""

    frames: list[FrameEntry]

    JSON: ClassVar[str] = "frames.json"

    def write(self, folder: Path) -> None:
        """Write frames.json into `folder`."""
        write_json(Path(folder) / self.JSON, [vars(entry) for entry in self.frames], indent=1)

    @classmethod
    def read(cls, folder: Path) -> "FramesRecord":
        """Read frames.json of a frames folder; StageError naming the file when it is missing or malformed."""
        path = Path(folder) / cls.JSON
        entries = read_json(path, "frames")
        try:
            return cls([FrameEntry(str(e["file"]), int(e["source_index"]), e["time_s"], float(e["sharpness"]),
                                   str(e["source"]), float(e["scale"])) for e in entries])
        except MALFORMED as error:
            raise StageError(f"{path}: malformed ({error!r}); expected a frames output folder") from error
