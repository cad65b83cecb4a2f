"""JSON files of the records: reading with errors that name the file, and the image-size check."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from stages.contract.errors import StageError

MALFORMED = (KeyError, ValueError, TypeError, OverflowError)  # what reading a record's parsed JSON raises when it
#                                                  lacks a key, holds another type, or a number too large (10^400)


def read_json(path: Path, producer: str) -> Any:
    """The parsed JSON of `path`; StageError naming the file and the stage that writes it when it is
    missing or not JSON."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError, RecursionError) as error:  # RecursionError: nesting too deep
        raise StageError(f"{path}: missing or not JSON ({error}); expected a {producer} output folder") from error


def write_json(path: Path, data: Any, indent: int | None = None) -> None:
    """Write `data` as JSON to `path`."""
    Path(path).write_text(json.dumps(data, indent=indent))


def check_image_size(path: Path, size: tuple[int, int], expected: tuple[int, int], image: str) -> None:
    """StageError unless the (width, height) a record file states equals the image's."""
    if tuple(size) != tuple(expected):
        raise StageError(f"{path} is for a {size[0]}x{size[1]} image, but the {image} is "
                         f"{expected[0]}x{expected[1]}")
