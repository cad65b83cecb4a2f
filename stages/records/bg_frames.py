"""bg_frames' output: a background video's frame slots. `bg_frames.json` says, per slot, which frame of the video
it holds (index, time, sharpness) or why it is empty, and how many frames each filter dropped; slot k's frame is
`images/%04d.png` and, for a video given with per-frame depth, its depth sidecar `images/%04d.depth.png` (uint16
millimetres, the sidecar bg_depth reads). A per-frame depth folder holds one depth file per video frame, named by
the frame's index (`depth_frame`). docs/stage_contracts.md, section bg_frames.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import ClassVar

from stages.contract.errors import StageError
from stages.records.files import MALFORMED, read_json, write_json


def depth_frame(index: int) -> str:
    """The name of video frame `index`'s depth file in a per-frame depth folder (uint16 millimetres of camera z)."""
    return f"{index:04d}.png"


@dataclass
class FrameSlot:
    """One frame slot: the video frame it holds, or why it is empty."""

    source_index: int | None = None  # the frame's index in the video; None when the slot is empty
    time_s: float | None = None  # its time in the video (None when the video gives no frame rate)
    sharpness: float | None = None  # variance of the Laplacian of the analysed frame
    empty: str = ""  # why the slot holds no frame ("" when it holds one)


@dataclass
class BgFramesRecord:
    """The frame slots of one background video."""

    video: str  # the video the frames came from
    slots: list[FrameSlot]
    counts: dict = field(default_factory=dict)  # frames decoded, dark, windows, blurred, duplicates_dropped, ...

    JSON: ClassVar[str] = "bg_frames.json"

    @staticmethod
    def image(slot: int) -> str:
        """Slot `slot`'s frame, relative to the bg_frames folder."""
        return f"images/{slot:04d}.png"

    @staticmethod
    def depth(slot: int) -> str:
        """Slot `slot`'s depth sidecar, relative to the bg_frames folder (for a video given with depth)."""
        return f"images/{slot:04d}.depth.png"

    def write(self, folder: Path) -> None:
        """Write bg_frames.json into `folder`."""
        write_json(Path(folder) / self.JSON, {"video": self.video, "slots": [asdict(s) for s in self.slots],
                                              "counts": self.counts}, indent=1)

    @classmethod
    def read(cls, folder: Path) -> "BgFramesRecord":
        """Read bg_frames.json of a bg_frames folder; StageError naming the file when it is missing or malformed."""
        path = Path(folder) / cls.JSON
        data = read_json(path, "bg_frames")
        try:
            slots = [FrameSlot(None if s["source_index"] is None else int(s["source_index"]), s["time_s"],
                               s["sharpness"], str(s["empty"])) for s in data["slots"]]
            return cls(str(data["video"]), slots, dict(data["counts"]))
        except MALFORMED as error:
            raise StageError(f"{path}: malformed ({error!r}); expected a bg_frames output folder") from error

    @classmethod
    def empty_reason(cls, image: Path) -> str | None:
        """Why the frame slot whose image is `image` (a path a graph points at inside a bg_frames folder) is empty;
        None when `image` is not a slot image of a bg_frames folder, or its slot holds a frame."""
        image, folder = Path(image), Path(image).parent.parent
        if not (folder / cls.JSON).is_file():
            return None
        slots = {cls.image(k): slot for k, slot in enumerate(cls.read(folder).slots)}
        slot = slots.get(image.relative_to(folder).as_posix())
        return (slot.empty or None) if slot is not None else None
