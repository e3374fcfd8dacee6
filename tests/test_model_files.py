"""Model files written back by the steppers that hold them: ``save`` then ``load_model`` steps
the same bits, and an existing file is never replaced unasked."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

import poisson_rs as pr


@pytest.mark.parametrize(
    ("make", "x0"),
    [
        (lambda: pr.taylor_integrator(pr.RigidBody(), 3, "exp"), [[1.0, 1.0, 2.0]]),
        (lambda: pr.load_model("default"), [[1.0, 1.0, 2.0]]),
        (lambda: pr.load_model("lotka_volterra_h01"), [[1.0, 0.8]]),
    ],
    ids=["taylor", "learned", "learned-log-canonical"],
)
def test_save_then_load_steps_the_same_bits(make: Any, x0: list[list[float]], tmp_path: Path):
    stepper = make()
    path = stepper.save(tmp_path / "m.safetensors")
    again = pr.load_model(path)
    np.testing.assert_array_equal(
        pr.integrate(again, x0, 0.1, 50), pr.integrate(stepper, x0, 0.1, 50)
    )
    before = path.read_bytes()
    with pytest.raises(ValueError, match=r"m\.safetensors"):
        stepper.save(path)
    assert path.read_bytes() == before  # kept
    assert stepper.save(path, overwrite=True) == path
