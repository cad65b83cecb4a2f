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
