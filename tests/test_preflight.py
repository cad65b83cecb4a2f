"""Input checks before any stage (stages/app/preflight.py): `plan` and `run` name each bad file with its cause, the
nodes that read it fail at once, and the datasets are planned without it."""
from __future__ import annotations

import json
import re
import time

import cv2
import numpy as np
import pytest

from stages.app.config import accept_data_file
from stages.app.pipeline import build_graph
from stages.app.preflight import check_inputs
from stages.contract.errors import StageError
from stages.engine.scheduler import Engine
from stages.records.coco_dataset import CocoDataset
from tests.factories.configs import CONF, compose_cfg, run_dag
from tests.factories.fuzz_seeds import ply_bytes
from tests.factories.user_data import DEFECTS, write_user_data


def user_graph(root, defects):
    """The graph and objects of a user's data config with the given defects (tests/factories/user_data.py)."""
    config = write_user_data(root, defects)
    cfg = compose_cfg(accept_data_file([f"data={config}"], CONF, root))
    return build_graph(cfg, root), [o.name for o in cfg.data.objects]


@pytest.mark.parametrize("defect, path, cause", [
    ("corrupt_video", "videos/broken.mp4", "cannot open video .* \\(corrupt, truncated or an unsupported codec\\)"),
    ("missing_video", "videos/ghost.mp4", "frames\\[ghost\\]: input .* not found"),
    ("truncated_photo", "photos/torn.jpg", "cannot read it as an image \\(image file is truncated"),
    ("bad_annotations", "test_bad", "annotations.json: not valid JSON"),
    ("wrong_categories", "test_names", "categories \\['cup'\\] are not objects of the data config"),
])
def test_each_bad_file_is_named_with_its_cause(tmp_path, defect, path, cause, cached_depth_model):
    graph, objects = user_graph(tmp_path, (defect,))
    problems = check_inputs(graph, objects)
    assert list(problems) == [tmp_path / path]
    assert str(tmp_path / path) in problems[tmp_path / path]
    assert re.search(cause, problems[tmp_path / path])


def test_good_data_has_no_problem(tmp_path, cached_depth_model):
    graph, objects = user_graph(tmp_path, ("photo_without_depth", "tum_plain_name"))
    assert check_inputs(graph, objects) == {}


@pytest.mark.parametrize("sidecar, cause", [
    ("small", "depth sidecar .*kitchen.depth.png: 48x36 \\(read as png_mm\\) does not match its photo"),
    ("eight_bit", "kitchen.depth.png: expected a single-channel 16-bit PNG, got mode 'L'"),
])
def test_a_depth_sidecar_header_is_checked_against_its_photo(tmp_path, sidecar, cause):
    config = write_user_data(tmp_path)
    depth = tmp_path / "photos" / "kitchen.depth.png"
    image = cv2.imread(str(depth), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(depth), image[::2, ::2] if sidecar == "small" else (image // 256).astype(np.uint8))
    cfg = compose_cfg(accept_data_file([f"data={config}"], CONF, tmp_path))
    problems = check_inputs(build_graph(cfg, tmp_path), [o.name for o in cfg.data.objects])
    assert list(problems) == [depth] and re.search(cause, problems[depth])


def test_a_malformed_test_set_is_found_before_training(tmp_path):
    """The eval of a test set whose annotations are broken is refused at the start, training is not."""
    graph, objects = user_graph(tmp_path, ("bad_annotations",))
    plan = {r.label: r for r in Engine(tmp_path / "cache").plan(graph.targets(None), check_inputs(graph, objects))}
    assert plan["eval[full@test_bad]"].status == "bad-input"
    assert "test_bad/annotations.json: not valid JSON" in plan["eval[full@test_bad]"].error
    assert plan["train_maskrcnn[full]"].status == plan["eval[full@test]"].status == "would-run"


@pytest.mark.parametrize("content, cause", [
    ('{"images": [', "not valid JSON"),
    ('{"images": []}', "needs the lists images, annotations, categories"),
    ('{"images": [{"id": 1, "file_name": "a.png", "width": 8, "height": 8}], "categories": [{"id": 1, "name": "mug"}], '
     '"annotations": [{"id": 1, "image_id": 2, "category_id": 1}]}', "1 annotations name an image or category id"),
    ('{"images": [{"id": 1}], "categories": [], "annotations": []}', "lacks the key 'file_name'"),
])
def test_a_malformed_coco_file_is_an_error_naming_it(tmp_path, content, cause):
    path = tmp_path / "annotations.json"
    path.write_text(content)
    with pytest.raises(StageError, match=f"{path}: .*{cause}"):
        CocoDataset.read(tmp_path)


@pytest.mark.slow
def test_plan_prints_every_problem_and_what_the_run_would_leave_out(tmp_path, cached_depth_model):
    """`python dag.py data=<file> run.action=plan` on a data config with every defect: each problem on
    screen with file and cause, the datasets planned without the bad objects and photos."""
    config = write_user_data(tmp_path / "data", DEFECTS)
    done, _ = run_dag(f"data={config}", "run.action=plan", f"run.cache_dir={tmp_path / 'cache'}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    out = done.stdout
    assert "input problems (5):" in out
    for name in ("videos/broken.mp4", "videos/ghost.mp4", "photos/torn.jpg", "test_bad/annotations.json",
                 "test_names/annotations.json"):
        assert str(tmp_path / "data" / name) in out, name
    assert "compose[full#0] without object broken: extract[broken] blocked (frames[broken] failed)" in out
    assert f"compose[full#0] without photo torn: background image {tmp_path / 'data' / 'photos' / 'torn.jpg'}" in out
    plan = {(r["stage"], r["item"]): r["status"] for r in json.loads((tmp_path / "run" / "plan.json").read_text())}
    assert plan[("compose", "full#0")] == plan[("train_maskrcnn", "full")] == plan[("eval", "full@test")] == "would-run"
    assert plan[("eval", "full@test_bad")] == plan[("frames", "ghost")] == "bad-input"


@pytest.mark.slow
def test_strict_run_with_a_bad_input_runs_nothing(tmp_path):
    config = write_user_data(tmp_path / "data", ("corrupt_video",))
    done, summary = run_dag(f"data={config}", "run.strict=true", f"run.cache_dir={tmp_path / 'cache'}", cwd=tmp_path)
    assert done.returncode == 1 and summary is None
    assert "run.strict: 1 input problems, nothing was run" in done.stdout + done.stderr
    assert not (tmp_path / "cache").exists()


def test_a_trained_model_that_does_not_read_is_named(tmp_path, cached_depth_model):
    (tmp_path / "photos").mkdir()
    cv2.imwrite(str(tmp_path / "photos" / "kitchen.jpg"), np.full((48, 64, 3), 128, np.uint8))
    (tmp_path / "plant.splat").write_bytes(bytes(40))  # not a whole number of 32-byte records
    cfg = compose_cfg(["data=folder", "data.objects=[{name: plant, height_m: 0.3, splat: plant.splat}]",
                       "data.backgrounds=photos", "data.test_sets=[]"])
    problems = check_inputs(build_graph(cfg, tmp_path), ["plant"])
    assert list(problems) == [tmp_path / "plant.splat"]
    assert "not a multiple of the 32-byte .splat record" in problems[tmp_path / "plant.splat"]


def test_a_lying_ply_header_is_a_named_input_problem_of_the_plan_in_under_3_s(tmp_path, cached_depth_model):
    """Issue 58: a model whose PLY header says 10^10 vertices while it holds 10 was a bare MemoryError that lost the
    whole plan; now it is one input problem naming the file, and the plan goes on."""
    (tmp_path / "photos").mkdir()
    cv2.imwrite(str(tmp_path / "photos" / "kitchen.jpg"), np.full((48, 64, 3), 128, np.uint8))
    data = ply_bytes().replace(b"element vertex 20\n", b"element vertex 10000000000\n")
    (tmp_path / "plant.ply").write_bytes(data[:data.index(b"end_header\n") + 11 + 10 * 104])
    cfg = compose_cfg(["data=folder", "data.objects=[{name: plant, height_m: 0.3, splat: plant.ply}]",
                       "data.backgrounds=photos", "data.test_sets=[]"])
    started = time.perf_counter()
    graph = build_graph(cfg, tmp_path)
    problems = check_inputs(graph, ["plant"])
    plan = {r.label: r for r in Engine(tmp_path / "cache").plan(graph.targets(None), problems)}
    assert time.perf_counter() - started < 3.0
    assert list(problems) == [tmp_path / "plant.ply"]
    assert f"Gaussian PLY {tmp_path / 'plant.ply'}: its header declares 10000000000 vertices" in problems[tmp_path / "plant.ply"]
    assert plan["extract[plant]"].status == "bad-input" and plan["bg_depth[kitchen]"].status == "would-run"
