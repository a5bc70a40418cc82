"""The one check of values headed for a port (ports, ROS 2, Foxglove), and the one way messages quote input."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from rtloop.errors import PortValueError
from rtloop.ipc.values import RejectedValues, validate_values
from rtloop.text import clip, shorten


@pytest.mark.parametrize(("values", "reason"), [
    ("1.5", "type"),            # numpy would parse it; a port takes numbers only
    (["1.5"], "type"),
    ([True], "type"),
    ([[1.0]], "shape"),
    ([1.0, 2.0], "length"),
    ([float("nan")], "nonfinite"),
    ([7.0], "range"),
])
def test_a_port_refuses_what_a_topic_refuses(values: object, reason: str) -> None:
    with pytest.raises(RejectedValues) as info:
        validate_values(values, 1, where="port 'p'", value_range=(-1.0, 1.0))
    assert info.value.reason == reason and str(info.value).startswith("port 'p': ")
    assert isinstance(info.value, PortValueError)


def test_a_single_number_is_one_value_and_the_result_is_a_copy() -> None:
    assert validate_values(0.5, 1).tolist() == [0.5]
    source = np.array([1.0, 2.0])
    out = validate_values(source, 2)
    source[0] = 9.0
    assert out.tolist() == [1.0, 2.0]


def test_a_refusal_survives_pickling_with_its_reason() -> None:
    try:
        validate_values([1.0], 2)
    except RejectedValues as error:
        copy = pickle.loads(pickle.dumps(error))
        assert (copy.reason, str(copy)) == ("length", str(error))


def test_quoted_input_is_cut_and_shows_its_end() -> None:
    text = shorten("x" * 10_000)
    assert len(text) == 80 and text.endswith("…xxx'")
    assert shorten([1, 2]) == "[1, 2]"
    assert clip("abcdef", 4) == "abc…" and clip("abc", 4) == "abc"
    assert len(clip("y" * 500, 60, keep_end=4)) == 60
