"""Commissioning ops' list arguments: good rows become floats, a bad one a bad_args naming it."""

from __future__ import annotations

from typing import Any

import pytest

from host.commissioning.ops import aims, image_targets, poses_arg
from host.control.ops import OpError


def test_rows_of_numbers_are_read_as_floats() -> None:
    three = [[100, 0.1, -0.2], [200, 0.0, 0.0], [300.5, -0.1, 0.2]]
    first = aims({"aims": three})[0]
    assert (first.s_mm, first.pan_rad, first.label) == (100.0, 0.1, "P1")
    assert isinstance(first.s_mm, float)
    poses = poses_arg({"aims": three[:1]})
    assert poses is not None
    assert poses[0].label == "s=100"
    assert poses_arg({}) is None
    assert image_targets({"image_targets": [[0.5, 0.25]]}) == ((0.5, 0.25),)


@pytest.mark.parametrize(
    ("read", "args", "key"),
    [
        (aims, {"aims": [[1, 2, 3], [1, 2, 3]]}, "aims"),  # fewer than 3 points
        (aims, {"aims": [[1, 2], [1, 2, 3], [1, 2, 3]]}, "aims"),  # a short row
        (aims, {"aims": [[1, 2, float("nan")]] * 3}, "aims"),
        (poses_arg, {"aims": "here"}, "aims"),
        (poses_arg, {"aims": [[1, 2, True]]}, "aims"),  # a flag is not a number
        (image_targets, {"image_targets": [[0.5, 1.0]]}, "image_targets"),  # on the edge
        (image_targets, {"image_targets": []}, "image_targets"),
    ],
)
def test_a_bad_row_is_a_bad_args_naming_its_key(read: Any, args: dict[str, Any], key: str) -> None:
    with pytest.raises(OpError) as err:
        read(args)
    assert err.value.code == "bad_args"
    assert key in str(err.value)
