"""Settings checked at start (stages/config.py CHOICES, stages/device.py) and data config files anywhere
(`data=/path/x.yaml`, stages/config.py accept_data_file)."""
from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from stages.config import CHOICES, accept_data_file, check_settings
from stages.device import DEVICES, choose_device
from tests.factories.configs import CONF, compose_cfg, run_dag
from tests.factories.user_data import GOOD_OBJECTS, write_user_data


def test_every_checked_setting_is_in_the_schema_and_the_defaults_pass():
    cfg = compose_cfg([])
    assert all(OmegaConf.select(cfg, key) is not None for key in CHOICES)
    check_settings(cfg)


@pytest.mark.parametrize("key", sorted(CHOICES))
def test_a_wrong_enumerated_setting_fails_naming_its_choices(key):
    cfg = compose_cfg([])
    bogus = ["none", "bogus"] if OmegaConf.is_list(OmegaConf.select(cfg, key)) else "bogus"
    OmegaConf.update(cfg, key, bogus)
    with pytest.raises(ValueError, match=f"{key}=.*bogus.* is not one of {', '.join(CHOICES[key])}"):
        check_settings(cfg)


def test_device_gpu_is_refused_naming_the_choices():
    with pytest.raises(ValueError, match=f"run.device='gpu' is not one of {', '.join(DEVICES)}"):
        choose_device("gpu")
    assert choose_device("cpu") == "cpu"


@pytest.mark.slow
def test_typos_in_values_stop_the_run_at_start(tmp_path):
    done, summary = run_dag("run.device=gpu", "bg_depth.provider=sidecr", f"run.cache_dir={tmp_path / 'cache'}",
                            cwd=tmp_path)
    assert done.returncode == 2 and summary is None and not (tmp_path / "cache").exists()
    message = done.stdout + done.stderr
    assert "run.device='gpu' is not one of auto, cpu, cuda" in message
    assert "bg_depth.provider='sidecr' is not one of sidecar, onnx, auto" in message


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
