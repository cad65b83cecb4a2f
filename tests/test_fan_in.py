"""Fan-in inputs (stages/contract/fan_in.py): what the pipeline builds is what a generator reads back."""
from __future__ import annotations

import pytest

from stages.contract.errors import StageError
from stages.contract.fan_in import check_kinds, fan_in, fanned, groups, left_out_items, per_object


def test_fan_in_round_trip_and_missing_inputs():
    objects = {"mug": {"sfm": "s1", "splat": "t1", "object": "e1"}, "can": {"sfm": "s2", "splat": "t2", "object": "e2"}}
    photos = {"bg1": {"background": "p1", "depth": "d1", "planes": "q1"}}
    object_kinds, photo_kinds = ("object", "splat"), ("background", "planes")
    inputs = {**fan_in(objects, object_kinds), **fan_in(photos, photo_kinds)}
    assert len(inputs) == 6 and fanned(inputs, "sfm") == {} and fanned(inputs, "planes") == {"bg1": "q1"}
    assert fanned(inputs, "object") == {"can": "e2", "mug": "e1"}
    found = per_object(inputs, ["mug", "can"], object_kinds, "gen")
    assert list(found) == ["mug", "can"] and found["can"] == {"object": "e2", "splat": "t2"}
    with pytest.raises(StageError, match=r"gen: no object has its inputs"):
        per_object(inputs, ["mug", "can"], ("sfm",), "gen")
    with pytest.raises(ValueError, match="unknown input kinds"):
        check_kinds(("planes",), ())


def test_an_object_without_inputs_is_left_out_and_one_with_some_is_an_error():
    objects = {"mug": {"sfm": "s1", "object": "e1"}, "can": {"sfm": "s2", "object": "e2"}}
    inputs = fan_in(objects, ("sfm", "object"))
    optional = groups(objects, ("sfm", "object"), "object")
    assert optional == {"sfm:mug": "object mug", "object:mug": "object mug",
                        "sfm:can": "object can", "object:can": "object can"}
    without_mug = {name: value for name, value in inputs.items() if optional[name] != "object mug"}
    assert list(per_object(without_mug, ["mug", "can"], ("sfm", "object"), "gen")) == ["can"]
    assert left_out_items({"object mug": "frames[mug] failed"}, ["mug", "can"], ["can"]) == {"object mug": "frames[mug] failed"}
    assert left_out_items({}, ["mug", "can"], ["can"]) == {"object mug": "no input given"}
    del without_mug["sfm:can"]
    with pytest.raises(StageError, match=r"gen: inputs \['sfm:can'\] missing"):
        per_object(without_mug, ["mug", "can"], ("sfm", "object"), "gen")
