"""Tests of predict (`python -m stages.app.predict`, dag.py's run.action=predict) and the model folder: the same
detections as eval, videos, ONNX, and every bad input named. A real tiny detector (tests/factories/detectors.py)."""
import json
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from stages.app.predict import main
from stages.engine.context import Context
from stages.eval.run import run as evaluate
from stages.lib.coco import rle_to_mask
from stages.lib.detection.model_folder import MODEL_JSON, WEIGHTS, open_model
from stages.lib.detection.onnx_export import compare_detections
from stages.lib.detection.postprocess import postprocess
from stages.lib.detection.sources import read_photo
from tests.factories.configs import ROOT
from tests.factories.detectors import train_tiny_detector, write_tiny_model_folder
from tests.factories.media import read_video_frames, write_video
from tests.factories.shapes import SHAPE_NAMES, write_shapes_dataset

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> dict[str, Path]:
    """The tiny detector's train_maskrcnn folder, a 4-photo test set and the detector's model folder."""
    root = tmp_path_factory.mktemp("predict")
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    model_dir = train_tiny_detector(root)
    testset = write_shapes_dataset(root / "test", 4, size=96, seed=1)
    folder = write_tiny_model_folder(root / "folder", model_dir, testset / "images" / "0000.png")
    torch.set_num_threads(before)
    return {"model_dir": model_dir, "testset": testset, "folder": folder}


def predict(*args: str) -> int:
    """`python -m stages.app.predict ARGS` in this process, on one thread; its exit status."""
    return main([*map(str, args), "--threads", "1"])


def predictions(out: Path) -> dict:
    return json.loads((out / "predictions.json").read_text())


def test_predict_on_test_photos_gives_evals_detections(trained, tmp_path):
    out = tmp_path / "eval"
    out.mkdir()
    inputs = {"model": trained["model_dir"], "testset": trained["testset"]}
    evaluate(Context("eval", "test", {"threads": 1}, inputs, out))
    assert predict(trained["folder"], trained["testset"] / "images", "--out", tmp_path / "p", "--conf", "0") == 0
    found = predictions(tmp_path / "p")
    assert found["complete"] and found["annotations"] == json.loads((out / "predictions.json").read_text())
    assert [image["file_name"] for image in found["images"]] == ["0000.png", "0001.png", "0002.png", "0003.png"]
    assert [c["name"] for c in found["categories"]] == SHAPE_NAMES


def test_filters_and_per_detection_files(trained, tmp_path, capsys):
    everything, out = tmp_path / "all", tmp_path / "filtered"
    assert predict(trained["folder"], trained["testset"] / "images", "--out", everything, "--no-overlays") == 0
    assert not (everything / "overlays").exists()
    assert predict(trained["folder"], trained["testset"] / "images", "--out", out, "--classes", "red_box",
                   "--max-det", "1", "--masks", "--crops") == 0
    assert "images/s" in capsys.readouterr().out.strip().splitlines()[-1]
    found = predictions(out)
    assert {a["category_id"] for a in found["annotations"]} == {1}
    assert all(sum(a["image_id"] == i for a in found["annotations"]) <= 1 for i in range(1, 5))
    best_red = [max((a for a in predictions(everything)["annotations"] if a["image_id"] == i and a["category_id"] == 1),
                    key=lambda a: a["score"], default=None) for i in range(1, 5)]
    assert found["annotations"] == [a for a in best_red if a is not None]
    assert all(a["score"] >= 0.5 for a in predictions(everything)["annotations"])
    first = found["annotations"][0]
    stem = Path(found["images"][first["image_id"] - 1]["file_name"]).stem
    mask = cv2.imread(str(out / "masks" / f"{stem}_0_red_box.png"), cv2.IMREAD_GRAYSCALE)
    assert np.array_equal(mask > 127, rle_to_mask(first["segmentation"]))
    assert (out / "crops" / "red_box" / f"{stem}_0.png").is_file()
    assert sorted(p.name for p in (out / "overlays").iterdir()) == ["0000.png", "0001.png", "0002.png", "0003.png"]


def test_a_video_becomes_an_mp4_of_as_many_frames_at_its_frame_rate(trained, tmp_path):
    photos = [cv2.imread(str(p)) for p in sorted((trained["testset"] / "images").iterdir())]
    video = write_video(tmp_path / "clip.mp4", photos * 2, fps=12.0)
    assert predict(trained["folder"], video, "--out", tmp_path / "p") == 0
    written = tmp_path / "p" / "overlays" / "clip.mp4"
    capture = cv2.VideoCapture(str(written))
    assert capture.isOpened() and capture.get(cv2.CAP_PROP_FPS) == pytest.approx(12.0)
    capture.release()
    assert len(read_video_frames(written)) == len(read_video_frames(video)) == 8
    found = predictions(tmp_path / "p")
    assert [(image["id"], image["frame"]) for image in found["images"]] == [(i + 1, i) for i in range(8)]


def test_onnx_gives_pytorchs_detections_on_two_photos_of_other_sizes(trained):
    """The graph was traced on a 96x96 photo; these are 160x96 and 96x136 (dynamic height and width)."""
    torch_model = open_model(trained["folder"])
    onnx_model = open_model(trained["folder"] / "model.onnx", threads=1)
    assert onnx_model.class_names == torch_model.class_names == SHAPE_NAMES and onnx_model.post == torch_model.post
    for name, size in (("0001.png", (160, 96)), ("0002.png", (96, 136))):
        image = cv2.resize(read_photo(trained["testset"] / "images" / name)[0], size)  # size: (width, height)
        found = [postprocess(m.detector.outputs(image), m.post, m.detector_size, 0.05)
                 for m in (torch_model, onnx_model)]
        check = compare_detections(*found)
        assert check["detections"] == check["reference_detections"] > 0 and check["same_labels"]
        assert check["max_box_difference_px"] <= 1.0 and check["min_mask_iou"] >= 0.99


def test_the_model_folder_works_copied_elsewhere(trained, tmp_path):
    copy = shutil.copytree(trained["folder"], tmp_path / "elsewhere" / "detector")
    saved = torch.load(copy / WEIGHTS, map_location="cpu", weights_only=True)
    assert saved["category_names"] == SHAPE_NAMES
    description = json.loads((copy / MODEL_JSON).read_text())
    assert description["input"]["image_size"] == 96 and description["post_processing"]["mask_threshold"] == 0.5
    assert "red_box, blue_disc" in (copy / "MODEL_CARD.md").read_text()
    assert description["card"]["onnx_check"]["min_mask_iou"] >= 0.99
    for model, out in ((trained["folder"], tmp_path / "a"), (copy, tmp_path / "b"),
                       (copy / "model.onnx", tmp_path / "c")):
        assert predict(model, trained["testset"] / "images" / "0002.png", "--out", out) == 0
    assert predictions(tmp_path / "a")["annotations"] == predictions(tmp_path / "b")["annotations"]
    assert len(predictions(tmp_path / "c")["annotations"]) == len(predictions(tmp_path / "a")["annotations"]) > 0


@pytest.mark.parametrize("case, message", [
    ("missing source", "source .*nowhere.* not found"),
    ("folder without photos", "source folder .*empty: no photos in it"),
    ("corrupt video", "video .*broken.mp4: cannot decode it"),
    ("glob without photos", "the pattern matches no photos"),
    ("missing model", "model .*ghost not found"),
    ("not a model", "model.pt: not a model; give a model folder"),
    ("folder without model.json", "not a model folder \\(it has no model.json\\)"),
    ("corrupt onnx", "junk.onnx: onnxruntime cannot load it"),
    ("newer model folder", "format version 99, but this version of Cut-and-Splat reads version 1"),
    ("unknown class", "classes \\['cat'\\] are not classes of the detector"),
    ("output folder in use", "exists and is not empty"),
])
def test_bad_inputs_are_named(trained, tmp_path, capsys, case, message):
    model, source, extra = trained["folder"], trained["testset"] / "images", []
    if case == "missing source":
        source = tmp_path / "nowhere"
    elif case == "folder without photos":
        source = tmp_path / "empty"
        source.mkdir()
        (source / "notes.txt").write_text("no photos here")
    elif case == "corrupt video":
        source = tmp_path / "broken.mp4"
        source.write_bytes(np.random.default_rng(0).bytes(4096))
    elif case == "glob without photos":
        source = tmp_path / "*.jpg"
    elif case == "missing model":
        model = tmp_path / "ghost"
    elif case == "not a model":
        model = trained["model_dir"] / "model.pt"
    elif case == "folder without model.json":
        model = trained["model_dir"]
    elif case == "corrupt onnx":
        model = tmp_path / "junk.onnx"
        model.write_bytes(b"not a graph")
    elif case == "newer model folder":
        model = shutil.copytree(trained["folder"], tmp_path / "newer")
        description = json.loads((model / MODEL_JSON).read_text())
        (model / MODEL_JSON).write_text(json.dumps({**description, "format_version": 99}))
    elif case == "unknown class":
        extra = ["--classes", "cat"]
    elif case == "output folder in use":
        (tmp_path / "out").mkdir()
        (tmp_path / "out" / "mine.txt").write_text("keep")
    assert predict(model, source, "--out", tmp_path / "out", *extra) == 2
    assert re.search(message, capsys.readouterr().err)


def test_an_unreadable_photo_among_good_ones_is_skipped_and_listed(trained, tmp_path, capsys):
    photos = shutil.copytree(trained["testset"] / "images", tmp_path / "photos")
    whole = (photos / "0001.png").read_bytes()
    (photos / "0001.png").write_bytes(whole[: len(whole) // 3])
    assert predict(trained["folder"], photos, "--out", tmp_path / "p") == 0
    found = predictions(tmp_path / "p")
    assert [image["file_name"] for image in found["images"]] == ["0000.png", "0002.png", "0003.png"]
    assert found["skipped"][0]["file_name"] == "0001.png" and "cannot read it" in found["skipped"][0]["error"]
    assert "1 unreadable, skipped" in capsys.readouterr().out


def test_a_list_file_and_a_glob_name_their_photos(trained, tmp_path):
    listing = tmp_path / "photos.txt"
    photos = trained["testset"] / "images"
    listing.write_text(f"# two photos\n{photos / '0003.png'}\n\n{photos / '0001.png'}\n")
    assert predict(trained["folder"], listing, "--out", tmp_path / "list") == 0
    assert [i["file_name"] for i in predictions(tmp_path / "list")["images"]] == [
        str(trained["testset"] / "images" / name) for name in ("0003.png", "0001.png")]
    assert predict(trained["folder"], trained["testset"] / "images" / "000[12].png", "--out", tmp_path / "glob") == 0
    assert len(predictions(tmp_path / "glob")["images"]) == 2


def ctrl_c_as_in_a_shell() -> None:
    """In the child before it starts: SIGINT at its default and unblocked, as a shell starts a command. A process
    inherits an ignored SIGINT, and Python then leaves it ignored: within the whole suite the pytest process has it
    so (a predict call of 400 frames finished at 41 images/s through the signal)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def test_an_interrupted_call_leaves_no_predictions_json(trained, tmp_path):
    photo = cv2.imread(str(trained["testset"] / "images" / "0000.png"))
    video = write_video(tmp_path / "long.mp4", [photo] * 400, fps=10.0)
    out = tmp_path / "p"
    command = [sys.executable, "-m", "stages.app.predict", str(trained["folder"]), str(video), "--out", str(out),
               "--threads", "1"]
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               preexec_fn=ctrl_c_as_in_a_shell)
    deadline = time.monotonic() + 120
    while not (out / "overlays").is_dir() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    process.send_signal(signal.SIGINT)
    output, err = process.communicate(timeout=60)
    assert process.returncode == 130, (output, err, sorted(p.name for p in out.iterdir()) if out.is_dir() else None)
    assert not (out / "predictions.json").exists()
    partial = json.loads((out / "predictions.partial.json").read_text())
    assert partial["complete"] is False and 0 < len(partial["images"]) < 400 and "KeyboardInterrupt" in partial["error"]
