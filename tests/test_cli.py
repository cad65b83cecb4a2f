"""The command line a newcomer meets: `python dag.py --help` is a short usage, not the whole config."""
from __future__ import annotations

import subprocess
import sys

from tests.factories.configs import ROOT


def test_help_is_a_short_usage():
    done = subprocess.run([sys.executable, str(ROOT / "dag.py"), "--help"], capture_output=True, text=True,
                          timeout=120, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    text = done.stdout
    for needed in ("run.action=plan", "run.until=extract", "+experiment=ablation", "data=/path/to/my_data.yaml",
                   "outputs/cache/<stage>/<key>/", "variant: cut_and_paste", "--cfg job"):
        assert needed in text, needed
    assert "powered by Hydra" not in text and len(text.splitlines()) < 40


def test_predict_has_a_usage_and_dag_names_the_command_that_trains_the_detector(tmp_path):
    done = subprocess.run([sys.executable, "-m", "stages.app.predict", "--help"], capture_output=True, text=True,
                          timeout=120, cwd=ROOT)
    assert done.returncode == 0 and "MODEL" in done.stdout.upper() and "--conf" in done.stdout, done.stderr
    done = subprocess.run([sys.executable, str(ROOT / "dag.py"), "run.action=predict", "predict.source=photos",
                           f"run.cache_dir={tmp_path / 'cache'}", f"hydra.run.dir={tmp_path / 'run'}"],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 2
    assert f"python dag.py run.cache_dir={tmp_path / 'cache'} run.until=train_maskrcnn" in done.stdout + done.stderr
