"""Settings checked at start (stages/app/config.py check_settings, the choices of stages/contract/choices.py,
stages/lib/device.py) and data config files anywhere (`data=/path/x.yaml`, stages/app/config.py accept_data_file)."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from stages.app.config import accept_data_file, check_settings, check_values, schema_keys
from stages.app.pipeline import build_graph
from stages.app.summary import data_line
from stages.engine.scheduler import Engine
from stages.lib.device import DEVICES, choose_device
from tests.factories.configs import CONF, ROOT, compose_cfg, composition_error, run_dag
from tests.factories.media import write_image
from tests.factories.user_data import GOOD_OBJECTS, write_user_data


def test_the_defaults_pass_and_every_schema_key_is_in_the_config():
    cfg = compose_cfg([])
    check_settings(cfg)
    assert all(OmegaConf.select(cfg, key, default="absent") != "absent" for key in schema_keys())


@pytest.mark.parametrize("key", ["cut_and_paste.blend_modes", "sfm.camera_model", "train_maskrcnn.backbone",
                                 "planes.point_sampling", "run.action"])
def test_a_wrong_enumerated_setting_fails_naming_its_choices(key):
    bogus = "[none,bogus]" if key.endswith("modes") else "bogus"
    assert "Invalid value 'bogus', expected one of [" in composition_error([f"{key}={bogus}"])


def test_a_plus_override_with_a_typo_fails_naming_the_nearest_key():
    check_settings(compose_cfg(["compose.num_images=10"]))
    with pytest.raises(ValueError, match=r"compose.num_imags is not a setting \(did you mean compose.num_images\?\); "
                                         r"frobnicate is not a setting$"):
        check_settings(compose_cfg(["+compose.num_imags=10", "+frobnicate=1"]))


def run_nodes(overrides: list[str]) -> list:
    """The nodes a run of the config with these overrides needs (the default data: the sample)."""
    cfg = compose_cfg(overrides)
    return Engine.closure(build_graph(cfg, ROOT).targets(cfg.run.until))


@pytest.mark.parametrize("experiment", [[], ["+experiment=ablation"], ["+experiment=real_dog"], ["+experiment=stability"]])
def test_values_out_of_range_fail_at_start_naming_the_setting(experiment):
    check_values(run_nodes(experiment))
    for setting, message in (("compose.group_share=2", "compose: group_share must be in [0, 1], got 2.0"),
                             ("eval.mask_owner_score=-0.5", "eval: mask_owner_score must be in [0, 1] or None"),
                             ("eval.mask_refine_eps=0", "eval: need mask_refine_radius >= 0 and mask_refine_eps > 0")):
        with pytest.raises(ValueError, match=re.escape(f"invalid setting: {message}")):
            check_values(run_nodes([*experiment, setting]))
    check_values(run_nodes([*experiment, "eval.mask_owner_score=null"]))


def test_device_gpu_is_refused_naming_the_choices():
    with pytest.raises(ValueError, match=f"run.device='gpu' is not one of {', '.join(DEVICES)}"):
        choose_device("gpu")
    assert choose_device("cpu") == "cpu"


@pytest.mark.slow
def test_typos_in_values_and_keys_stop_the_run_at_start(tmp_path):
    done, summary = run_dag("bg_depth.provider=sidecr", f"run.cache_dir={tmp_path / 'cache'}", cwd=tmp_path)
    assert done.returncode != 0 and summary is None and not (tmp_path / "cache").exists()
    assert "Invalid value 'sidecr', expected one of [sidecar, model, auto]" in done.stdout + done.stderr
    done, summary = run_dag("+compose.num_imags=10", "run.action=plan", f"run.cache_dir={tmp_path / 'cache'}",
                            cwd=tmp_path)
    assert done.returncode == 2 and summary is None and not (tmp_path / "run" / "plan.json").exists()
    assert "compose.num_imags is not a setting (did you mean compose.num_images?)" in done.stdout + done.stderr


def test_data_accepts_a_file_anywhere(tmp_path, monkeypatch):
    config = write_user_data(tmp_path / "elsewhere")
    monkeypatch.setenv("HOME", str(tmp_path))
    for given in (str(config), "elsewhere/my_data.yaml", "~/elsewhere/my_data.yaml"):
        argv = accept_data_file(["dag.py", f"data={given}", "run.action=plan"], CONF, tmp_path)
        assert argv[0] == "dag.py" and argv[2] == "run.action=plan" and argv[1].startswith("data=my_data_")
        cfg = compose_cfg(argv[1:])
        assert cfg.data.source == "folder" and [o.name for o in cfg.data.objects] == list(GOOD_OBJECTS)


def test_data_option_names_and_missing_files(tmp_path):
    assert accept_data_file(["data=folder.yaml"], CONF, tmp_path) == ["data=folder"]
    assert accept_data_file(["data=sample", "variant=full"], CONF, tmp_path) == ["data=sample", "variant=full"]
    with pytest.raises(SystemExit, match="data=nowhere/x.yaml: no such file .*; give a data config file .* "
                                         "or an option of conf/data: folder, sample"):
        accept_data_file(["data=nowhere/x.yaml"], CONF, tmp_path)


def test_a_data_file_with_a_typo_fails_naming_the_key(tmp_path):
    config = tmp_path / "typo.yaml"
    config.write_text("source: folder\nbackround: photos\n")
    with pytest.raises(Exception, match="backround"):
        compose_cfg(accept_data_file([f"data={config}"], CONF, tmp_path))


def write_smallest_data_file(root: Path, source: str | None = None) -> Path:
    """The smallest data file that looks right (issue 55): one object's photo folder, a folder of 4 photos without
    depth sidecars, one test set; `source` written when given."""
    (root / "plush_dog" / "images").mkdir(parents=True)
    (root / "bg").mkdir()
    for name in ("kitchen", "office", "hall", "shop"):
        write_image(root / "bg" / f"{name}.jpg", np.full((48, 64, 3), 120, np.uint8))
    (root / "plush_dog_test" / "images").mkdir(parents=True)
    config = root / "dog.yaml"
    config.write_text((f"source: {source}\n" if source else "") + f"""objects:
  - {{name: plush_dog, height_m: 0.25, video: {root / 'plush_dog' / 'images'}}}
backgrounds: {root / 'bg'}
test_sets:
  - {{name: real, path: {root / 'plush_dog_test'}}}
""")
    return config


def test_a_data_file_without_source_is_the_users_data_alone(tmp_path, cached_depth_model):
    config = write_smallest_data_file(tmp_path)
    cfg = compose_cfg(accept_data_file([f"data={config}"], CONF, tmp_path))
    assert cfg.data.source == "folder" and cfg.data.indomain_backgrounds is None and not cfg.data.sample_backgrounds
    graph = build_graph(cfg, tmp_path)
    assert "sample" not in graph.nodes
    assert sorted(n.item for n in graph.nodes["bg_depth"]) == ["hall", "kitchen", "office", "shop"]
    assert [n.item for n in graph.nodes["frames"]] == ["plush_dog"]
    assert [n.item for n in graph.nodes["eval"]] == ["full@real"]
    assert data_line(graph.nodes) == (f"data: 1 object: plush_dog ({tmp_path / 'plush_dog' / 'images'}); 4 "
                                      f"background photos: 4 from {tmp_path / 'bg'}; test sets: real "
                                      f"({tmp_path / 'plush_dog_test'})")


def test_a_data_file_mixes_in_the_sample_only_when_it_says_so(tmp_path):
    config = write_smallest_data_file(tmp_path, source="sample")
    cfg = compose_cfg(accept_data_file([f"data={config}"], CONF, tmp_path))
    assert cfg.data.source == "sample"  # the sample's objects replaced by the file's, its photos added to the sample's
    mixed = tmp_path / "mixed.yaml"
    mixed.write_text(config.read_text().replace("source: sample\n", "sample_backgrounds: true\n"))
    cfg = compose_cfg(accept_data_file([f"data={mixed}"], CONF, tmp_path))
    graph = build_graph(cfg, tmp_path)
    photos = [n.item for n in graph.nodes["bg_depth"]]
    assert cfg.data.source == "folder" and len(photos) == 4 + cfg.sample.num_backgrounds
    assert f"{cfg.sample.num_backgrounds} of the sample" in data_line(graph.nodes)


def test_a_data_file_without_objects_fails_at_start(tmp_path):
    config = tmp_path / "empty.yaml"
    config.write_text("backgrounds: photos\n")
    cfg = compose_cfg(accept_data_file([f"data={config}"], CONF, tmp_path))
    with pytest.raises(ValueError, match="data.objects is empty"):
        build_graph(cfg, tmp_path)
    config.write_text("- a list\n")
    with pytest.raises(SystemExit, match="expected a mapping of data settings"):
        accept_data_file([f"data={config}"], CONF, tmp_path)


def test_plan_starts_with_the_data_line(tmp_path, cached_depth_model):
    config = write_smallest_data_file(tmp_path)
    done, _ = run_dag(f"data={config}", "run.action=plan", f"run.cache_dir={tmp_path / 'cache'}", cwd=tmp_path)
    assert done.stdout.splitlines()[0].startswith("data: 1 object: plush_dog ("), done.stdout + done.stderr
    plan = json.loads((tmp_path / "run" / "plan.json").read_text())
    assert sum(r["stage"] == "bg_depth" for r in plan) == 4 and not any(r["stage"] == "sample" for r in plan)
