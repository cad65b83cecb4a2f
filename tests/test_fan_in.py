"""Fan-in inputs (stages/fan_in.py): what the pipeline builds is what a generator reads back."""
from __future__ import annotations

import pytest

from stages.context import StageError
from stages.fan_in import InputKinds, fan_in, fanned, per_object


def test_fan_in_round_trip_and_missing_inputs():
    objects = {"mug": {"sfm": "s1", "splat": "t1", "object": "e1"}, "can": {"sfm": "s2", "splat": "t2", "object": "e2"}}
    photos = {"bg1": {"background": "p1", "depth": "d1", "planes": "q1"}}
    kinds = InputKinds(per_object=("object", "splat"), per_photo=("background", "planes"))
    inputs = {**fan_in(objects, kinds.per_object), **fan_in(photos, kinds.per_photo)}
    assert len(inputs) == 6 and fanned(inputs, "sfm") == {} and fanned(inputs, "planes") == {"bg1": "q1"}
    assert fanned(inputs, "object") == {"can": "e2", "mug": "e1"}
    assert per_object(inputs, ["mug", "can"], kinds.per_object, "gen") == [{"object": "e1", "splat": "t1"},
                                                                          {"object": "e2", "splat": "t2"}]
    with pytest.raises(StageError, match=r"gen: inputs \['sfm:mug', 'sfm:can'\] missing"):
        per_object(inputs, ["mug", "can"], ("sfm",), "gen")
    with pytest.raises(ValueError, match="unknown input kinds"):
        InputKinds(per_object=("planes",), per_photo=())
