"""Files written by torch.save (a detector's model.pt, a training checkpoint's last.pt) read back within bounds.

torch.save writes a zip archive of a pickle and one stored (uncompressed) record per tensor. `load_torch_file`
checks that the file is such an archive whose records fit in it before torch reads it, loads it with
`weights_only=True` (tensors, numbers, strings and containers only: no code runs), turns whatever torch
raises for a broken file into a StageError naming it, and refuses anything but the dict both files are (a flipped
byte can make the pickle a function).
"""
from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any

import torch

from stages.contract.errors import StageError
from stages.lib.file_checks import regular_file


def load_torch_file(path: Path, what: str) -> dict[str, Any]:
    """The dict torch.save wrote to `path` (`what` names it in errors, e.g. "detector file"); StageError when it is
    not a readable torch.save zip archive whose records fit in the file, torch cannot load it, or it is no dict."""
    path = Path(path)
    size = regular_file(path, what)
    try:
        with zipfile.ZipFile(path) as archive:
            declared = sum(info.file_size for info in archive.infolist())
    except Exception as error:  # noqa: BLE001 - zipfile raises BadZipFile, NotImplementedError, EOFError, ...
        raise StageError(f"{what} {path}: not a file written by torch.save (not a zip archive: {error})") from error
    if declared > size:
        raise StageError(f"{what} {path}: its records declare {declared} bytes, but the file holds {size}; it is "
                         "truncated or corrupt")
    try:
        loaded = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - torch raises RuntimeError, UnpicklingError, EOFError, ... for bad files
        raise StageError(f"{what} {path}: torch cannot read it ({type(error).__name__}: {str(error)[:200]})") from error
    if not isinstance(loaded, dict):
        raise StageError(f"{what} {path}: holds a {type(loaded).__name__}, not the dict torch.save wrote")
    return loaded
