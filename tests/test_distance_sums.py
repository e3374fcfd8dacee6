"""Hamiltonians that are sums over distances (poisson_rs.distance_sums, the core's compiled
gradient in rust/distance_sum.rs): which H are recognised, the field against autograd, RK4
against the interpreted field program, and bad tables refused naming the field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import poisson_rs as pr
from poisson_rs import _core
from poisson_rs.distance_sums import LOG, POWER, distance_terms
from poisson_rs.scenes import load_scene

SCENES = Path(__file__).resolve().parent.parent / "scenes"


def _vortices() -> pr.ExpressionSystem:
    return load_scene(SCENES / "point_vortices.toml").system


def _on_the_vortex_bracket(text: str) -> pr.ExpressionSystem:
    return pr.with_hamiltonian(_vortices().base, text)


# H text → (radial kinds, powers) of its distance terms in the order written.
RECOGNISED = {
    "vortices": (None, [LOG, LOG, LOG], [0.0, 0.0, 0.0]),
    "kepler": ("(x2**2 + x4**2)/2 - 1/sqrt(x1**2 + x3**2)", [POWER], [-0.5]),
    "powers and a polynomial": (
        "0.3*((x1 - x3)**2 + (x2 - x4)**2 + (x5 - x6)**2)**-1.5 + 2*((x1 - x5)**2)**0.7"
        " - log(sqrt((x3 - x1)**2)) + x1*x2**2 - 3",
        [POWER, POWER, LOG],
        [-1.5, 0.7, 0.0],
    ),
    "inverse square, scaled inside": (
        "1.5/(2*(x1 - x3)**2 + 2*(x2 - x4)**2) + x5",
        [POWER],
        [-1.0],
    ),
    "a distance to the power one": ("sqrt((x1 - x3)**2 + (x2 - x4)**2)", [POWER], [0.5]),
}

NOT_RECOGNISED = {
    "a sine beside a distance": "sin(x1) + log((x1 - x3)**2 + (x2 - x4)**2)",
    "a constant inside the log": "log(x1**2 + 1)",
    "a product of logs": "log((x1 - x3)**2)*log((x2 - x4)**2)",
    "unequal scales of the squares": "log(2*(x1 - x3)**2 + (x2 - x4)**2)",
    "not a difference": "log((x1 - x3 + x5)**2)",
    "the origin in one coordinate only": "((x1 - x3)**2 + x2**2)**-0.5",
    "a polynomial alone": "x1*x2 + x3**2",
    "four coordinates a point": "log((x1-x2)**2 + (x3-x4)**2 + (x5-x6)**2 + (x1-x6)**2)",
}


def _system(case: str) -> pr.ExpressionSystem:
    text = RECOGNISED[case][0]
    return _vortices() if text is None else _on_the_vortex_bracket(text)


@pytest.mark.parametrize("case", list(RECOGNISED))
def test_distance_sums_are_recognised_term_by_term(case: str) -> None:
    s = _system(case)
    _, kinds, powers = RECOGNISED[case]
    assert s.distances is not None
    assert s.distances.radial.tolist() == kinds
    np.testing.assert_array_equal(s.distances.power, powers)


def test_the_vortices_weights_and_points_are_read_off_h() -> None:
    d = _vortices().distances
    assert d is not None
    # −(1/4π)(ln r₁₂² + ½ ln r₁₃² + ½ ln r₂₃²), points (x1, x2), (x3, x4), (x5, x6).
    np.testing.assert_allclose(d.weight, np.array([1.0, 0.5, 0.5]) * -1 / (4 * np.pi), rtol=1e-15)
    assert d.dims.tolist() == [2, 2, 2]
    assert d.first[:, :2].tolist() == [[0, 1], [0, 1], [2, 3]]
    assert d.second[:, :2].tolist() == [[2, 3], [4, 5], [4, 5]]
    assert len(d.coeffs) == 0


@pytest.mark.parametrize("case", list(NOT_RECOGNISED))
def test_other_hamiltonians_keep_the_interpreted_program(case: str) -> None:
    s = _on_the_vortex_bracket(NOT_RECOGNISED[case])
    assert s.distances is None
    assert distance_terms(s.h.program, s.dim) is None


@pytest.mark.parametrize("case", list(RECOGNISED))
def test_the_compiled_field_equals_autograds(case: str) -> None:
    """π∇H from the core's distance terms against torch autograd of H's own program."""
    s = _system(case)
    rng = np.random.default_rng(3)
    x = rng.uniform(-1.5, 1.5, size=(64, 6))
    xt = torch.tensor(x, dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(s.hamiltonian(xt).sum(), xt)
    want = np.einsum("nij,nj->ni", s.bivector(x), grad.numpy())
    np.testing.assert_allclose(s.vector_field(x), want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("case", ["vortices", "kepler", "powers and a polynomial"])
def test_rk4_on_the_distance_terms_follows_the_interpreted_program(case: str) -> None:
    """The same RK4 with ∇H compiled and with the field program interpreted: rounding apart,
    one trajectory (64 states, 40 steps)."""
    s = _system(case)
    rng = np.random.default_rng(4)
    base = np.array([1.0, 0.0, -0.5, 0.6, -0.3, -0.8])
    x0 = base + 0.1 * rng.uniform(-1.0, 1.0, size=(64, 6))
    tables = (*s.tape, *s.terms.tables())

    def run(distances: object) -> np.ndarray:
        traj, _ = _core.rollout_hamiltonian_field(
            "rk4", *tables, x0, 0.01, 40, 40, program=s.field_program, distances=distances
        )
        return traj

    assert s.distances is not None
    compiled, interpreted = run(s.distances.table()), run(None)
    np.testing.assert_allclose(compiled, interpreted, rtol=1e-12, atol=1e-12)
    assert np.abs(compiled[:, -1] - x0).max() > 1e-3  # the states moved


def _table(**change: object) -> tuple[object, ...]:
    t = {
        "radial": np.array([0], dtype=np.int64),
        "weight": np.array([1.0]),
        "power": np.array([0.0]),
        "dims": np.array([2], dtype=np.int64),
        "first": np.array([[0, 1, 0]], dtype=np.int64),
        "second": np.array([[2, 3, 0]], dtype=np.int64),
        "coeffs": np.zeros(0),
        "exponents": np.zeros((0, 6), dtype=np.int64),
    }
    t.update(change)
    return tuple(t.values())


BAD_TABLES = {
    "radial": ({"radial": np.array([2], dtype=np.int64)}, "radial must be 0"),
    "weight": ({"weight": np.array([np.nan])}, "weight must be finite"),
    "power": ({"radial": np.array([1], dtype=np.int64)}, "power must be finite and nonzero"),
    "dims": ({"dims": np.array([4], dtype=np.int64)}, "dims must be 1, 2 or 3"),
    "first": ({"first": np.array([[0, 6, 0]], dtype=np.int64)}, "first out of range"),
    "second": ({"second": np.array([[-1, 3, 0]], dtype=np.int64)}, "second out of range"),
    "same points": ({"second": np.array([[0, 1, 0]], dtype=np.int64)}, "same coordinates"),
    "first's shape": ({"first": np.array([[0, 1]], dtype=np.int64)}, r"first must have shape"),
    "rows": ({"weight": np.array([1.0, 2.0])}, "one row per term"),
    "polynomial columns": (
        {"coeffs": np.ones(1), "exponents": np.ones((1, 5), dtype=np.int64)},
        "must have 6 columns",
    ),
    "negative exponent": (
        {"coeffs": np.ones(1), "exponents": -np.ones((1, 6), dtype=np.int64)},
        "must not be negative",
    ),
}


@pytest.mark.parametrize("case", list(BAD_TABLES))
def test_bad_distance_tables_are_refused_naming_the_field(case: str) -> None:
    s = _vortices()
    change, message = BAD_TABLES[case]
    x = np.zeros((2, 6)) + np.arange(6)
    with pytest.raises(ValueError, match=f"distances: .*{message}"):
        _core.hamiltonian_field(
            *s.tape, *s.terms.tables(), x, program=s.field_program, distances=_table(**change)
        )
    # The table the module builds is accepted, and gives the program's field.
    assert s.distances is not None
    np.testing.assert_allclose(
        _core.hamiltonian_field(*s.tape, *s.terms.tables(), x, distances=s.distances.table()),
        _core.hamiltonian_field(*s.tape, *s.terms.tables(), x, program=s.field_program),
        rtol=1e-13,
    )
