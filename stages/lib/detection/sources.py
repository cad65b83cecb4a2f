"""What predict runs on: one photo, a folder of photos, a glob, a text file listing photos, or a video, read as RGB
frames in order. A photo that cannot be read is a frame without an image and with the reason (skipped and listed by
the caller); a source that cannot be read at all is a FileNotFoundError or ValueError naming it."""
from __future__ import annotations

import glob
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
from PIL import Image, ImageOps

from stages.lib.imageio import IMAGE_SUFFIXES, list_images

VIDEO_SUFFIXES = (".avi", ".m4v", ".mkv", ".mov", ".mp4")
LIST_SUFFIXES = (".txt",)  # a text file: one photo path a line (relative to the file's folder), '#' comments


@dataclass
class Frame:
    """One photo or video frame: image_id (1-based, in source order), file_name (the photo's path as listed, or the
    video's name), frame (its index in the video; None for a photo), image (RGB uint8 [H, W, 3]; None when it could
    not be read, then `error` says why)."""

    image_id: int
    file_name: str
    frame: int | None
    image: np.ndarray | None
    error: str = ""


@dataclass
class Source:
    """A source checked by open_source: kind "photos" (`photos`, each with the name it is listed under) or "video"
    (`video`, `fps`, `frame_count` as the file announces it)."""

    spec: str
    kind: str
    photos: list[tuple[Path, str]] = field(default_factory=list)
    video: Path | None = None
    fps: float = 0.0
    frame_count: int = 0

    @property
    def count(self) -> int:
        """How many frames the source has (a video's as announced)."""
        return len(self.photos) if self.kind == "photos" else self.frame_count

    def frames(self) -> Iterator[Frame]:
        """The frames in order (photos decoded one at a time)."""
        if self.kind == "photos":
            for image_id, (path, name) in enumerate(self.photos, start=1):
                image, error = read_photo(path)
                yield Frame(image_id, name, None, image, error)
            return
        capture = cv2.VideoCapture(str(self.video))
        try:
            index = 0
            while True:
                ok, bgr = capture.read()
                if not ok:
                    break
                yield Frame(index + 1, self.video.name, index, np.ascontiguousarray(bgr[..., ::-1]))
                index += 1
        finally:
            capture.release()


def read_photo(path: Path) -> tuple[np.ndarray | None, str]:
    """A photo as RGB uint8 [H, W, 3] (EXIF orientation applied) and "", or None and why it cannot be read."""
    try:
        with Image.open(path) as image:
            image.load()
            rgb = np.asarray(ImageOps.exif_transpose(image).convert("RGB"))
    except Exception as error:  # PIL raises many types for a missing or broken file
        return None, f"cannot read it as an image ({error})"
    return rgb, ""


def open_video(path: Path, spec: str) -> Source:
    """A video source; ValueError naming the file when OpenCV cannot decode its first frame."""
    capture = cv2.VideoCapture(str(path))
    try:
        ok = capture.isOpened() and capture.read()[0]
        fps, count = capture.get(cv2.CAP_PROP_FPS), int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    finally:
        capture.release()
    if not ok:
        raise ValueError(f"video {path}: cannot decode it (corrupt, truncated or an unsupported codec); re-encode "
                         "it as MP4 (H.264 or mp4v) or give its frames as photos")
    return Source(spec, "video", video=path, fps=fps if fps > 0 else 30.0, frame_count=max(count, 0))


def listed_photos(path: Path) -> list[tuple[Path, str]]:
    """The photos a text file lists (paths relative to its folder; blank lines and '#' comments skipped)."""
    photos = []
    for line in path.read_text().splitlines():
        entry = line.strip()
        if entry and not entry.startswith("#"):
            photo = Path(entry).expanduser()
            photos.append((photo if photo.is_absolute() else path.parent / photo, entry))
    if not photos:
        raise ValueError(f"list file {path}: lists no photos (one path a line)")
    return photos


def open_source(spec: str | Path) -> Source:
    """The source `spec` names: a photo, a folder (its photos, IMAGE_SUFFIXES, not its subfolders), a glob pattern
    (its photos), a video (VIDEO_SUFFIXES) or a .txt list of photos. FileNotFoundError or ValueError naming it when
    it does not exist, holds no photos, or is a video OpenCV cannot decode."""
    text = str(spec)
    path = Path(text).expanduser()
    if not path.exists() and any(c in text for c in "*?["):
        matches = sorted(Path(p) for p in glob.glob(str(path), recursive=True))
        photos = [(p, str(p)) for p in matches if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
        if not photos:
            raise FileNotFoundError(f"source {text}: the pattern matches no photos ({', '.join(IMAGE_SUFFIXES)})")
        return Source(text, "photos", photos)
    if not path.exists():
        raise FileNotFoundError(f"source {text} not found (give a photo, a folder, a glob, a video or a .txt list)")
    if path.is_dir():
        photos = [(p, p.name) for p in list_images(path)]
        if not photos:
            raise ValueError(f"source folder {path}: no photos in it ({', '.join(IMAGE_SUFFIXES)}; subfolders are not "
                             "searched: give a glob like 'folder/**/*.jpg' for those)")
        return Source(text, "photos", photos)
    suffix = path.suffix.lower()
    if suffix in VIDEO_SUFFIXES:
        return open_video(path, text)
    if suffix in LIST_SUFFIXES:
        return Source(text, "photos", listed_photos(path))
    if suffix in IMAGE_SUFFIXES:
        return Source(text, "photos", [(path, path.name)])
    raise ValueError(f"source {path}: not a photo ({', '.join(IMAGE_SUFFIXES)}), a video "
                     f"({', '.join(VIDEO_SUFFIXES)}) or a .txt list of photos")
