"""The readers of files from strangers, as the fuzz tests call them (tests/test_fuzz_readers.py), each with its
valid seed (tests/factories/fuzz_seeds.py), its named cases (lying headers, NaNs, what a user's tool writes
wrong) and the header fields where a declared count or size can lie. Every case must end in a StageError naming
the file or in a clean result. The readers import their libraries when called: a child process loads only its
reader's (torch only for the torch-file reader).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from tests.factories import fuzz_seeds as seeds
from tests.factories.fuzz_inputs import Case, Field, deeply_nested, packed


@dataclass(frozen=True)
class Reader:
    """A reader under test: `seed` writes its valid files into a folder, `read` is given `target` inside it."""

    name: str
    seed: Callable[[Path], None]
    target: str
    read: Callable[[Path], Any]
    named: Callable[[dict[str, bytes]], list[Case]]
    fields: dict[str, dict[str, Field]] = field(default_factory=dict)
    torch: bool = False


def _write(name: str, data: Callable[[], bytes]) -> Callable[[Path], None]:
    return lambda folder: (folder / name).write_bytes(data())


# PLY ----------------------------------------------------------------------------------------------------------
def _read_ply(path: Path) -> Any:
    from stages.lib.gaussians.gaussian_files import read_ply_vertices
    return read_ply_vertices(path).shape


def _header(edit: Callable[[list[str]], list[str]]) -> bytes:
    lines = (["ply", "format binary_little_endian 1.0", f"element vertex {seeds.PLY_COUNT}"]
             + [f"property float {name}" for name in seeds.PLY_NAMES] + ["end_header"])
    return seeds.ply_bytes(edit(lines))


def _ply_cases(files: dict[str, bytes]) -> list[Case]:
    data = files["model.ply"]
    edits = {
        "the lying header of issue 58: element vertex 10000000000": lambda h: h[:2] + ["element vertex 10000000000"] + h[3:],
        "vertex count -5": lambda h: h[:2] + ["element vertex -5"] + h[3:],
        "vertex count 'ten'": lambda h: h[:2] + ["element vertex ten"] + h[3:],
        "vertex count 0": lambda h: h[:2] + ["element vertex 0"] + h[3:],
        "format ascii 1.0": lambda h: h[:1] + ["format ascii 1.0"] + h[2:],
        "a list property": lambda h: h[:3] + ["property list uchar int vertex_indices"] + h[3:],
        "a property without a name": lambda h: h[:3] + ["property float"] + h[3:],
        "no opacity property": lambda h: [line for line in h if line != "property float opacity"],
        "a repeated property": lambda h: h[:3] + ["property float x"] + h[3:],
        "7 f_rest properties (no SH degree)": lambda h: [line for line in h if line != "property float f_rest_8"
                                                         and line != "property float f_rest_7"],
        "element face before vertex": lambda h: h[:2] + ["element face 3", "property float a"] + h[2:],
        "no vertex element": lambda h: [line for line in h if not line.startswith(("element", "property"))],
        "100 000 comment lines": lambda h: h[:2] + ["comment x"] * 100_000 + h[2:],
        "a face element after the vertices": lambda h: h[:-1] + ["element face 0", "property float a", "end_header"],
    }
    values = {f"NaN {name}": (name, math.nan) for name in ("x", "f_dc_0", "f_rest_4", "opacity", "rot_2")}
    values.update({f"infinite {name}": (name, math.inf) for name in ("z", "scale_1")})
    return ([Case(name, "model.ply", _header(edit)) for name, edit in edits.items()]
            + [Case(name, "model.ply", seeds.ply_with_value(*value)) for name, value in values.items()]
            + [Case("no end_header", "model.ply", data[:data.index(b"end_header")]),
               Case("10 MB without a newline", "model.ply", b"ply\n" + b"a" * 10_000_000),
               Case("Windows line ends in the header", "model.ply", _crlf_ply(data))])


def _crlf_ply(data: bytes) -> bytes:
    header, body = data.split(b"end_header\n", 1)
    return header.replace(b"\n", b"\r\n") + b"end_header\r\n" + body


def _ply_count(data: bytes, value: int) -> bytes:
    return data.replace(f"element vertex {seeds.PLY_COUNT}\n".encode(), f"element vertex {value}\n".encode(), 1)


# .splat -------------------------------------------------------------------------------------------------------
def _read_splat(path: Path) -> Any:
    from stages.lib.gaussians.gaussian_files import read_splat_records
    return read_splat_records(path).shape


def _splat_cases(files: dict[str, bytes]) -> list[Case]:
    values = {"NaN position": (math.nan, 0.05), "infinite position": (math.inf, 0.05), "NaN scale": (0.1, math.nan),
              "zero scale": (0.1, 0.0), "negative scale": (0.1, -0.05)}
    return ([Case(name, "model.splat", seeds.splat_bytes(*value)) for name, value in values.items()]
            + [Case("size not a multiple of 32 bytes", "model.splat", files["model.splat"] + b"12345"),
               Case("one record", "model.splat", files["model.splat"][:32])])


# COLMAP -------------------------------------------------------------------------------------------------------
def _read_colmap(path: Path) -> Any:
    from stages.lib.gaussians.colmap import read_colmap_scene
    return len(read_colmap_scene(path).frames)


def _colmap_fields() -> dict[str, dict[str, Field]]:
    count: Field = lambda data, value: packed(data, 0, "Q", value % 2 ** 64)  # noqa: E731
    keypoints: Field = lambda data, value: packed(data, data.index(b"\0", 76) + 1, "Q", value % 2 ** 64)  # noqa: E731
    return {"sparse/cameras.bin": {"camera count": count,
                                   "width": lambda data, value: packed(data, 16, "Q", value % 2 ** 64)},
            "sparse/images.bin": {"image count": count, "keypoints of the first image": keypoints},
            "sparse/points3D.bin": {"point count": count,
                                    "track length of the first point": lambda d, v: packed(d, 51, "Q", v % 2 ** 64)},
            "sparse/frames.bin": {"frame count": count, "data ids": lambda d, v: packed(d, 72, "I", v % 2 ** 32)},
            "sparse/rigs.bin": {"rig count": count, "sensors": lambda d, v: packed(d, 12, "I", v % 2 ** 32)}}


def _colmap_cases(files: dict[str, bytes]) -> list[Case]:
    cameras, images, points = files["sparse/cameras.bin"], files["sparse/images.bin"], files["sparse/points3D.bin"]
    name_end = images.index(b"\0", 76)
    return [Case("a SIMPLE_PINHOLE camera (3 parameters)", "sparse/cameras.bin", packed(cameras, 12, "i", 0)),
            Case("NaN focal length", "sparse/cameras.bin", packed(cameras, 32, "d", math.nan)),
            Case("NaN camera rotation", "sparse/images.bin", packed(images, 12, "d", math.nan)),
            Case("infinite camera position", "sparse/images.bin", packed(images, 44, "d", math.inf)),
            Case("an image of camera 7, which is not there", "sparse/images.bin", packed(images, 68, "I", 7)),
            Case("an image name without its end", "sparse/images.bin", images[:name_end]),
            Case("NaN point position", "sparse/points3D.bin", packed(points, 16, "d", math.nan)),
            Case("a track naming keypoint 99 of image 1", "sparse/points3D.bin", packed(points, 63, "I", 99)),
            Case("a track naming image 42", "sparse/points3D.bin", packed(points, 59, "I", 42))]


# depth sidecars -----------------------------------------------------------------------------------------------
def _read_depth(fmt: str) -> Callable[[Path], Any]:
    def read(path: Path) -> Any:
        from stages.lib.depth.formats import read_sidecar_depth, sidecar_size
        sidecar_size(path, fmt)
        return read_sidecar_depth(path, fmt).shape
    return read


def _depth_png_cases(files: dict[str, bytes]) -> list[Case]:
    data = files["photo.depth.png"]
    return [Case("40000 x 40000 declared (IHDR, CRC right)", "photo.depth.png", seeds.png_size(data, 40000, 40000)),
            Case("an 8-bit PNG", "photo.depth.png", seeds.png_bytes(np.full((48, 64), 9, np.uint8))),
            Case("an RGB PNG", "photo.depth.png", seeds.png_bytes(np.full((48, 64, 3), 9, np.uint8))),
            Case("all zero (no depth)", "photo.depth.png", seeds.png_bytes(np.zeros((48, 64), np.uint16)))]


def _npy_cases(files: dict[str, bytes]) -> list[Case]:
    depth = seeds.depth_npy()
    with_nan = depth.copy()
    with_nan[:10] = np.nan
    lies = {"shape (100000, 100000) declared": {"descr": "<f4", "fortran_order": False, "shape": (100000, 100000)},
            "shape (-1, 64) declared": {"descr": "<f4", "fortran_order": False, "shape": (-1, 64)},
            "an object dtype": {"descr": "|O", "fortran_order": False, "shape": (48, 64)}}
    arrays = {"all NaN": np.full((48, 64), np.nan, np.float32), "NaN in some rows (no depth there)": with_nan,
              "infinite values": np.full((48, 64), np.inf, np.float32), "a 3-channel array": np.ones((48, 64, 3)),
              "a 1-D array": np.ones(64), "a 0-D array": np.array(1.0), "complex numbers": depth.astype(np.complex64),
              "booleans": depth > 2, "big-endian float64": depth.astype(">f8"), "int16 millimetres": depth.astype(np.int16)}
    return ([Case(name, "photo.depth.npy", seeds.npy_bytes(depth, header)) for name, header in lies.items()]
            + [Case(name, "photo.depth.npy", seeds.npy_bytes(array)) for name, array in arrays.items()]
            + [Case("a version 2.0 header", "photo.depth.npy", seeds.npy_bytes(depth, version=(2, 0))),
               Case("header length 65535 declared", "photo.depth.npy",
                    packed(files["photo.depth.npy"], 8, "H", 65535))])


def _pgm_cases(files: dict[str, bytes]) -> list[Case]:
    return [Case("maxval 255 (8-bit)", "photo.depth.pgm", seeds.pgm_bytes(maxval=255)),
            Case("maxval 70000", "photo.depth.pgm", seeds.pgm_bytes(maxval=70000)),
            Case("100000 x 100000 declared", "photo.depth.pgm", seeds.pgm_bytes(100000, 100000)),
            Case("a width of 400 digits", "photo.depth.pgm", b"P5\n" + b"9" * 400 + b" 48\n65535\n"),
            Case("an ASCII PGM (P2)", "photo.depth.pgm", b"P2\n64 48\n65535\n" + b"1 " * 3072),
            Case("values above 11 bits in both byte orders", "photo.depth.pgm",
                 seeds.pgm_bytes(raw=np.full((48, 64), 0x0F0F, np.uint16)))]


def _pgm_fields() -> dict[str, dict[str, Field]]:
    width: Field = lambda data, value: data.replace(b"64 48", f"{value} 48".encode(), 1)  # noqa: E731
    return {"photo.depth.pgm": {"width": width}}


# COCO ---------------------------------------------------------------------------------------------------------
def _seed_coco(folder: Path) -> None:
    from stages.lib.coco import CocoBuilder

    (folder / "images").mkdir()
    (folder / "images" / "0000.png").write_bytes(seeds.photo_png())
    builder = CocoBuilder(["mug"])
    image_id = builder.add_image("0000.png", seeds.WIDTH, seeds.HEIGHT)
    mask = np.zeros((seeds.HEIGHT, seeds.WIDTH), bool)
    mask[10:30, 20:40] = True
    builder.add_instance(image_id, 1, mask)
    builder.dataset.write(folder)


def _read_coco(path: Path) -> Any:
    from stages.records.coco_dataset import CocoDataset
    return len(CocoDataset.read(path).annotations)


def _coco_cases(files: dict[str, bytes]) -> list[Case]:
    document = json.loads(files["annotations.json"])

    def edited(edit: Callable[[dict], None]) -> bytes:
        copy = json.loads(json.dumps(document))
        edit(copy)
        return json.dumps(copy).encode()

    def setter(kind: str, key: str, value: Any) -> Callable[[dict], None]:
        return lambda d: d[kind][0].__setitem__(key, value)

    edits = {"NaN in a box": setter("annotations", "bbox", [1, 2, math.nan, 4]),
             "an infinite box": setter("annotations", "bbox", [1, 2, math.inf, 4]),
             "a box of strings": setter("annotations", "bbox", ["1", "2", "3", "4"]),
             "a box of booleans": setter("annotations", "bbox", [True, True, True, True]),
             "a polygon with NaN": setter("annotations", "segmentation", [[1, 2, 3, math.nan, 5, 6]]),
             "an RLE of another size": lambda d: d["annotations"][0]["segmentation"].__setitem__("size", [1, 1]),
             "image width NaN": setter("images", "width", math.nan),
             "image width 10^400": setter("images", "width", 10 ** 400),
             "image width 'wide'": setter("images", "width", "wide"),
             "an image of 10^9 x 10^9 pixels": lambda d: d["images"][0].update(width=10 ** 9, height=10 ** 9),
             "file_name /etc/passwd": setter("images", "file_name", "/etc/passwd"),
             "file_name ../annotations.json": setter("images", "file_name", "../annotations.json"),
             "file_name a number": setter("images", "file_name", 5),
             "file_name with a NUL byte": setter("images", "file_name", "0000\0.png"),
             "an image id that is a list": setter("images", "id", [1]),
             "a category name that is a list": setter("categories", "name", ["mug"]),
             "annotations that are numbers": lambda d: d.__setitem__("annotations", [1, 2]),
             "no categories": lambda d: d.__setitem__("categories", [])}
    return ([Case(name, "annotations.json", edited(edit)) for name, edit in edits.items()]
            + [Case("10 000 nested arrays", "annotations.json", deeply_nested(10_000)),
               Case("UTF-16 encoded", "annotations.json", files["annotations.json"].decode().encode("utf-16")),
               Case("a byte-order mark", "annotations.json", b"\xef\xbb\xbf" + files["annotations.json"])])


# the records of the stages' JSON files ------------------------------------------------------------------------
def _seed_records(folder: Path) -> None:
    from stages.records.cameras import CameraFrame, CamerasRecord
    from stages.records.capture_truth import CaptureTruth
    from stages.records.depth import DepthRecord
    from stages.records.extract import ExtractRecord
    from stages.records.frames import FrameEntry, FramesRecord
    from stages.records.planes import PlacementPlane, PlanesRecord

    K, up = np.array([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]]), np.array([0.0, -1.0, 0.0])
    CamerasRecord(seeds.WIDTH, seeds.HEIGHT, [CameraFrame("0000.png", K, np.eye(4), seeds.WIDTH, seeds.HEIGHT)]).write(folder)
    DepthRecord("sidecar", True, K, seeds.WIDTH, seeds.HEIGHT, seeds.depth_npy(), "png_mm").write(folder)
    ExtractRecord(np.array([0.0, 0.0, 1.0]), np.zeros(3), 2.0).write(folder)
    FramesRecord([FrameEntry("images/0000.jpg", 0, 0.0, 10.0, "video.mp4", 1.0)]).write(folder)
    PlanesRecord(K, seeds.WIDTH, seeds.HEIGHT, up, True,
                 [PlacementPlane(up, np.zeros(3), 1.0, np.zeros((5, 3)), np.zeros((5, 2)))]).write(folder)
    np.save(folder / "object_points.npy", np.zeros((10, 3), np.float32))
    CaptureTruth("mug", 0.1, K, seeds.WIDTH, seeds.HEIGHT, 10.0, {0: np.eye(4)}, np.array([0.0, 0.0, 1.0]),
                 np.zeros(3), "object_points.npy").write(folder)
    (folder / "photo.json").write_text(json.dumps({"K": K.tolist()}))


def _read_records(path: Path) -> Any:
    from stages.lib.depth.intrinsics import read_intrinsics_json
    from stages.records.cameras import CamerasRecord
    from stages.records.capture_truth import CaptureTruth
    from stages.records.depth import DepthRecord
    from stages.records.extract import ExtractRecord
    from stages.records.frames import FramesRecord
    from stages.records.planes import PlanesRecord

    read = [record.read(path) for record in (CamerasRecord, DepthRecord, ExtractRecord, FramesRecord, PlanesRecord)]
    return len(read), CaptureTruth.read(path).object_points(path).shape, read_intrinsics_json(path / "photo.json").shape


def _records_cases(files: dict[str, bytes]) -> list[Case]:
    def edited(file: str, edit: Callable[[Any], None]) -> bytes:
        document = json.loads(files[file])
        edit(document)
        return json.dumps(document).encode()

    edits = {"NaN in a camera's K (cameras.json)": ("cameras.json", lambda d: d["frames"][0]["K"][0].__setitem__(0, math.nan)),
             "an infinite viewmat (cameras.json)": ("cameras.json", lambda d: d["frames"][0]["viewmat"][0].__setitem__(3, math.inf)),
             "a frame width of 10^400 (cameras.json)": ("cameras.json", lambda d: d["frames"][0].__setitem__("width", 10 ** 400)),
             "a frame width of infinity (cameras.json)": ("cameras.json", lambda d: d["frames"][0].__setitem__("width", math.inf)),
             "NaN in K (depth.json)": ("depth.json", lambda d: d["K"][1].__setitem__(1, math.nan)),
             "a height of NaN (extract.json)": ("extract.json", lambda d: d.__setitem__("height", math.nan)),
             "counts that are a list (extract.json)": ("extract.json", lambda d: d.__setitem__("counts", [1])),
             "a frame index of infinity (frames.json)": ("frames.json", lambda d: d[0].__setitem__("source_index", math.inf)),
             "NaN in K (planes.json)": ("planes.json", lambda d: d["K"][0].__setitem__(2, math.nan)),
             "NaN in a true viewmat (gt.json)": ("gt.json", lambda d: d["frames"][0]["viewmat"][2].__setitem__(2, math.nan)),
             "K of strings (photo.json)": ("photo.json", lambda d: d.__setitem__("K", [["a"] * 3] * 3)),
             "K of 10^400 (photo.json)": ("photo.json", lambda d: d["K"][0].__setitem__(0, 10 ** 400))}
    return ([Case(name, file, edited(file, edit)) for name, (file, edit) in edits.items()]
            + [Case(f"10 000 nested arrays ({file})", file, deeply_nested(10_000))
               for file in ("cameras.json", "depth.json", "gt.json", "photo.json")]
            + [Case("depth.npy declaring 100000 x 100000", "depth.npy",
                    seeds.npy_bytes(seeds.depth_npy(), {"descr": "<f4", "fortran_order": False, "shape": (100000, 100000)})),
               Case("object_points.npy of Python objects", "object_points.npy",
                    seeds.npy_bytes(np.zeros(3), {"descr": "|O", "fortran_order": False, "shape": (3,)}))])


# photos -------------------------------------------------------------------------------------------------------
def _read_photo(path: Path) -> Any:
    from stages.lib.imageio import load_photo
    return load_photo(path).shape


def _photo_cases(files: dict[str, bytes]) -> list[Case]:
    png = files["photo.png"]
    return [Case("40000 x 40000 declared (IHDR, CRC right)", "photo.png", seeds.png_size(png, 40000, 40000)),
            Case("12000 x 9000 declared, 4 KB of data", "photo.png", seeds.png_size(png, 12000, 9000)),
            Case("a JPEG declaring 65500 x 65500 (SOF0)", "photo.png", seeds.jpeg_size(seeds.photo_jpeg(), 65500, 65500)),
            Case("a truncated JPEG", "photo.png", seeds.photo_jpeg()[:600]),
            Case("a 16-bit grey PNG", "photo.png", seeds.png_bytes(np.full((48, 64), 30000, np.uint16))),
            Case("10 x 10 pixels (too small)", "photo.png", seeds.png_bytes(np.zeros((10, 10, 3), np.uint8)))]


def _png_fields(name: str) -> dict[str, dict[str, Field]]:
    return {name: {"IHDR width": lambda data, value: seeds.png_size(data, value, seeds.HEIGHT),
                   "IHDR height": lambda data, value: seeds.png_size(data, seeds.WIDTH, value)}}


def _seed_photo_folder(folder: Path) -> None:
    (folder / "photos").mkdir()
    (folder / "photos" / "a.png").write_bytes(seeds.photo_png())
    (folder / "photos" / "b.jpg").write_bytes(seeds.photo_jpeg())


def _read_photo_folder(path: Path) -> Any:
    from stages.frames.run import read_image_folder
    capture = read_image_folder(path, 640, [])
    return [frame.image.shape for frame in capture.frames()]


def _photo_folder_cases(files: dict[str, bytes]) -> list[Case]:
    return [Case("a 40000 x 40000 PNG among the photos", "photos/a.png", seeds.png_size(files["photos/a.png"], 40000,
                                                                                       40000)),
            Case("a JPEG declaring 65500 x 65500 among the photos", "photos/b.jpg",
                 seeds.jpeg_size(files["photos/b.jpg"], 65500, 65500))]


# videos -------------------------------------------------------------------------------------------------------
def _read_video(path: Path) -> Any:
    from stages.lib.capture.video_frames import read_video
    return sum(1 for _ in read_video(path, 640).frames())


def _video_cases(files: dict[str, bytes]) -> list[Case]:
    data = files["video.mp4"]
    return [Case("65535 x 65535 declared (stsd)", "video.mp4", seeds.mp4_size(data, 65535, 65535)),
            Case("0 x 0 declared (stsd)", "video.mp4", seeds.mp4_size(data, 0, 0)),
            Case("the moov box cut off", "video.mp4", data[:data.index(b"moov") + 64])]


def _video_fields() -> dict[str, dict[str, Field]]:
    return {"video.mp4": {"width": lambda data, value: seeds.mp4_size(data, value, seeds.HEIGHT),
                          "mdat size": seeds.mdat_size}}


# torch files --------------------------------------------------------------------------------------------------
def _read_torch(path: Path) -> Any:
    from stages.lib.torch_files import load_torch_file
    return sorted(load_torch_file(path, "detector file"))


def _torch_cases(files: dict[str, bytes]) -> list[Case]:
    import io
    import zipfile

    text = io.BytesIO()
    with zipfile.ZipFile(text, "w") as archive:
        archive.writestr("notes.txt", "hello")
    data = files["model.pt"]
    return [Case("a zip of a text file", "model.pt", text.getvalue()),
            Case("a pickle calling os.system", "model.pt", b"cos\nsystem\n(S'true'\ntR."),
            Case("the tensor record cut off", "model.pt", data[:data.index(b"PK\x01\x02") - 40])]


READERS = {reader.name: reader for reader in (
    Reader("ply", _write("model.ply", seeds.ply_bytes), "model.ply", _read_ply, _ply_cases,
           {"model.ply": {"vertex count": _ply_count}}),
    Reader("splat", _write("model.splat", seeds.splat_bytes), "model.splat", _read_splat, _splat_cases),
    Reader("colmap", lambda folder: seeds.colmap_model(folder / "sparse"), "sparse", _read_colmap, _colmap_cases,
           _colmap_fields()),
    Reader("depth_png", _write("photo.depth.png", seeds.depth_png), "photo.depth.png", _read_depth("png_mm"),
           _depth_png_cases, _png_fields("photo.depth.png")),
    Reader("depth_npy", _write("photo.depth.npy", lambda: seeds.npy_bytes(seeds.depth_npy())), "photo.depth.npy",
           _read_depth("npy_m"), _npy_cases),
    Reader("depth_pgm", _write("photo.depth.pgm", seeds.pgm_bytes), "photo.depth.pgm", _read_depth("nyu"),
           _pgm_cases, _pgm_fields()),
    Reader("coco", _seed_coco, ".", _read_coco, _coco_cases),
    Reader("records", _seed_records, ".", _read_records, _records_cases),
    Reader("photo", _write("photo.png", seeds.photo_png), "photo.png", _read_photo, _photo_cases,
           _png_fields("photo.png")),
    Reader("photo_folder", _seed_photo_folder, "photos", _read_photo_folder, _photo_folder_cases,
           _png_fields("photos/a.png")),
    Reader("video", lambda folder: (folder / "video.mp4").write_bytes(seeds.video_bytes(folder)), "video.mp4",
           _read_video, _video_cases, _video_fields()),
    Reader("torch_file", _write("model.pt", seeds.torch_file), "model.pt", _read_torch, _torch_cases,
           {"model.pt": {"record size": seeds.zip_record_size}}, torch=True),
)}
