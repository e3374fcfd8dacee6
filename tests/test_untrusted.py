"""The untrusted-input wrapper: every failure becomes one InputError naming input and field."""

from __future__ import annotations

import json
import math

import pytest

from poisson_rs.untrusted import InputError, parsing


@pytest.mark.parametrize(
    "bad",
    [
        lambda: json.loads("[" * 100_000 + "]" * 100_000),  # RecursionError
        lambda: math.exp(1e300),  # OverflowError
        lambda: {}["missing"],  # KeyError
        lambda: int(None),  # type: ignore[arg-type]  # TypeError
        lambda: float("x"),  # ValueError
    ],
)
def test_any_failure_becomes_one_input_error(bad) -> None:
    with pytest.raises(InputError) as info, parsing("scene s.toml", "h"):
        bad()
    message = str(info.value)
    assert message.startswith("scene s.toml, field h: ")
    assert "\n" not in message
    assert isinstance(info.value, ValueError)
    assert info.value.__cause__ is None and info.value.__suppress_context__


def test_inner_error_keeps_its_field_and_memory_error_passes() -> None:
    with pytest.raises(InputError, match="field inner"), parsing("model m", "outer"):
        with parsing("model m", "inner"):
            raise TypeError("x")
    with pytest.raises(MemoryError), parsing("model m"):
        raise MemoryError
    with parsing("model m"):
        pass


def test_long_messages_are_cut() -> None:
    with pytest.raises(InputError) as info, parsing("f"):
        raise ValueError("y" * 10_000)
    assert len(str(info.value)) < 400
