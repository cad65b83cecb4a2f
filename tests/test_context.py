"""What a stage gets from the engine (stages/engine/context.py): without a terminal, progress is a log line per
interval instead of redrawn bars; settings given directly are checked against the stage's config when the stage asks
for them (the engine checks every node's at start: tests/test_engine*.py)."""
from __future__ import annotations

import logging
from pathlib import Path

import pytest

from stages.app.pipeline import STAGES
from stages.contract.errors import StageError
from stages.engine.context import Context, LoggedProgress
from stages.train_maskrcnn.spec import TrainMaskrcnnConfig


def test_without_a_terminal_progress_is_one_log_line_per_interval(caplog):
    ctx = Context("splat_train", "mug", {}, {}, Path("."), log=logging.getLogger("stages.splat_train.run"))
    progress = ctx.progress(range(4), total=4)  # pytest captures stderr: not a terminal
    assert isinstance(progress, LoggedProgress)
    progress.every_s = 0.0
    with caplog.at_level(logging.INFO, logger="stages.splat_train.run"):
        for step in progress:
            progress.set_postfix(loss=f"{1.0 / (step + 1):.2f}")
    assert [r.getMessage().split(" after ")[0] for r in caplog.records] == [f"splat_train[mug]: {k} / 4" for k in
                                                                             range(1, 5)]
    assert caplog.records[-1].getMessage().endswith("(loss=0.25)")

    caplog.clear()
    quiet = LoggedProgress(iter(range(1000)), ctx.log, "eval[x]", initial=5)  # default interval: 30 s
    assert sum(1 for _ in quiet) == 1000 and quiet.count == 1005 and not caplog.records


def test_settings_given_directly_are_checked_like_the_command_line(tmp_path):
    """A stage run without the engine (tests, benchmarks) still refuses a wrong choice, an unknown key, a wrong type
    or a value out of range, naming the setting, when it asks for its typed settings; they are built once."""
    for params, key in (({"schedule": "stpe"}, "train_maskrcnn.schedule"),
                        ({"shcedule": "step"}, "train_maskrcnn.shcedule"), ({"lr": "fast"}, "train_maskrcnn.lr"),
                        ({"closeup_share": 1.5}, "closeup_share")):
        with pytest.raises(StageError, match=key):
            Context(stage="train_maskrcnn", item="full", params=params, inputs={}, out=tmp_path).typed(
                TrainMaskrcnnConfig)
    ctx = Context(stage="train_maskrcnn", item="full", params={"schedule": "step"}, inputs={}, out=tmp_path)
    settings = ctx.typed(TrainMaskrcnnConfig)
    assert settings.schedule == "step" and ctx.typed(TrainMaskrcnnConfig) is settings
    assert all(stage.config.__name__.lower() == name.replace("_", "") + "config" for name, stage in STAGES.items())
