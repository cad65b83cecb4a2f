import argparse

import pytest

from benchmarks.lib.settings import add_set_option, changed_settings, setting


def test_a_value_is_read_as_json_where_it_parses_else_kept_as_text():
    assert setting("num_images=40") == ("num_images", 40)
    assert setting("relight=none") == ("relight", "none")
    assert setting("sizes=[1, 2]") == ("sizes", [1, 2])
    assert setting("lr=1e-3") == ("lr", 1e-3)
    assert setting("formula=a=b") == ("formula", "a=b")  # the first '=' splits
    for text in ("num_images", "=40"):
        with pytest.raises(argparse.ArgumentTypeError, match="wants KEY=VALUE"):
            setting(text)


def test_the_option_takes_several_pairs_and_repeats():
    parser = argparse.ArgumentParser()
    add_set_option(parser, "the settings")
    args = parser.parse_args(["--set", "a=1", "b=x", "--set", "c=true"])
    assert args.set == [("a", 1), ("b", "x"), ("c", True)]
    assert parser.parse_args([]).set == []
    with pytest.raises(SystemExit):
        parser.parse_args(["--set", "a", "1"])  # the old spelling, KEY JSON, is refused at start


def test_changes_are_checked_against_the_defaults_by_name():
    defaults = {"iterations": 2000, "lr": 0.01, "backend": "auto", "sizes": [1, 2], "dense": True, "cap": None}
    assert changed_settings([("iterations", 12), ("lr", 1), ("sizes", [3]), ("cap", "x")], defaults) == {
        "iterations": 12, "lr": 1, "sizes": [3], "cap": "x"}
    with pytest.raises(SystemExit, match="--set iteration=...: 'iteration' is not a setting here"):
        changed_settings([("iteration", 12)], defaults)
    for key, value, kind in (("iterations", 1.5, "int"), ("lr", "low", "float"), ("dense", 1, "bool"),
                             ("iterations", True, "int"), ("backend", 3, "str")):
        with pytest.raises(SystemExit, match=f"is not a {kind} like its default"):
            changed_settings([(key, value)], defaults)
