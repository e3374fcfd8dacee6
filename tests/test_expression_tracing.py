"""A Hamiltonian given as a callable on torch tensors (pr.with_hamiltonian(structure, fn)),
traced into the grammar: the core's H and field against the callable's own values and autograd
gradient, the same integrator bit for bit as the equivalent text, names, pickling, and every
refusal in one error naming 'hamiltonian'."""

from __future__ import annotations

import math
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import poisson_rs as pr
from poisson_rs.expression_tracing import trace_hamiltonian, tracing_names
from poisson_rs.expressions import MAX_CHARS, Expression, ExpressionError
from poisson_rs.scenes import load_scene

SCENES = Path(__file__).resolve().parent.parent / "scenes"


def _pendulum_structure() -> Any:
    return load_scene(SCENES / "extended_pendulum_pnn.toml").system


def _vortices_structure() -> Any:
    return load_scene(SCENES / "point_vortices.toml").system


def pnn_pendulum(x: torch.Tensor) -> torch.Tensor:
    """PNN's extended pendulum, as one writes it in torch."""
    u, v, r = x.unbind(-1)
    return 0.5 * u**2 - torch.cos(v) + u * (r - u**2 - v**2)


def vortices(x: torch.Tensor) -> torch.Tensor:
    """Three point vortices Γ = (1, 0.5, 0.25) in torch, with a loop over the pairs."""
    gamma = (1.0, 0.5, 0.25)
    h = 0.0
    for a in range(3):
        for b in range(a + 1, 3):
            d2 = (x[..., 2 * a] - x[..., 2 * b]) ** 2 + (x[..., 2 * a + 1] - x[..., 2 * b + 1]) ** 2
            h = h - gamma[a] * gamma[b] * torch.log(d2) / (8 * math.pi)
    return h


def rigid_potential(x: torch.Tensor) -> torch.Tensor:
    inertia = torch.tensor([1.5, 2.0, 2.5], dtype=torch.float64)
    return (x**2 / (2 * inertia)).sum(-1) + torch.sqrt(1 + (x * x).sum(-1)) + x[..., 2].cos()


CASES = {
    "extended pendulum": (_pendulum_structure, pnn_pendulum, 0.8),
    "point vortices": (_vortices_structure, vortices, None),
    "rigid body potential": (lambda: pr.RigidBody((1.5, 2.0, 2.5)), rigid_potential, 1.0),
}


def _states(structure: Any, scale: float | None, n: int, seed: int) -> np.ndarray:
    if scale is None:  # the vortices' demo states, perturbed (no two points collide)
        base = np.asarray(structure.demo_states, dtype=np.float64)
        rng = np.random.default_rng(seed)
        return base[rng.integers(0, len(base), n)] + 0.05 * rng.normal(size=(n, structure.dim))
    return np.random.default_rng(seed).uniform(-scale, scale, (n, structure.dim))


@pytest.mark.parametrize("case", list(CASES))
def test_the_cores_h_and_field_are_the_callables_value_and_autograd_gradient(case: str) -> None:
    make, fn, scale = CASES[case]
    structure = make()
    system = pr.with_hamiltonian(structure, fn)
    x = _states(structure, scale, 16, 1)
    xt = torch.tensor(x, requires_grad=True)
    h = fn(xt)
    (grad,) = torch.autograd.grad(h.sum(), xt)
    field = np.einsum("kij,kj->ki", np.asarray(structure.bivector(x)), grad.numpy())
    np.testing.assert_allclose(system.hamiltonian(x), h.detach().numpy(), rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(system.vector_field(x), field, rtol=1e-12, atol=1e-13)


def test_the_traced_text_is_the_one_a_user_would_write_and_steps_bit_for_bit() -> None:
    structure = _pendulum_structure()
    traced = pr.with_hamiltonian(structure, pnn_pendulum)
    written = pr.with_hamiltonian(structure, "u**2/2 - cos(v) + u*(r - u**2 - v**2)")
    assert traced.h.text == "0.5*u**2 - cos(v) + u*(r - u**2 - v**2)"
    x0 = _states(structure, 0.8, 4, 2)
    for method in ("rk4", "midpoint"):
        a = pr.integrate(pr.classical(traced, method), x0, 0.05, 200)
        b = pr.integrate(pr.classical(written, method), x0, 0.05, 200)
        # u**2/2 and 0.5*u**2 are the same rounding: the trajectories are the same bits.
        assert np.array_equal(a, b)
    jets = pr.integrate(traced.taylor_integrator(3), x0, 0.1, 20)
    assert np.abs(jets - pr.integrate(written.taylor_integrator(3), x0, 0.1, 20)).max() == 0.0
    assert pickle.loads(pickle.dumps(traced)).h.text == traced.h.text


@pytest.mark.parametrize(
    ("fn", "text"),
    [
        (lambda x: x[..., 0] * x[..., 1] - x[..., 2], "x1*x2 - x3"),
        (lambda x: x[0] - (x[1] - x[2]), "x1 - (x2 - x3)"),
        (lambda x: x[0] / (x[1] * x[2]), "x1/(x2*x3)"),
        (lambda x: -(x[0] ** 2), "-x1**2"),
        (lambda x: (-x[0]) ** 2, "(-x1)**2"),
        (lambda x: x[0] * -2 + 3, "x1*-2.0 + 3.0"),
        (lambda x: x[0] + (-0.5), "x1 + -0.5"),
        (lambda x: x[0] ** -1 + x[1] ** 0.25, "x1**-1 + x2**0.25"),
        (lambda x: torch.pow(torch.square(x[..., 0]), 3), "(x1**2)**3"),
        (lambda x: torch.sum(torch.exp(x[..., 1:]), dim=-1), "exp(x2) + exp(x3)"),
        (lambda x: np.sin(x[..., 0]) + np.tanh(x[..., 1]), "sin(x1) + tanh(x2)"),
        (lambda x: math.e ** x[0] + 2 ** x[1], "exp(x1) + exp(0.6931471805599453*x2)"),
        (lambda x: ((x - torch.tensor([1.0, 0.0, 2.0])) ** 2).sum(), None),
        (lambda x: 4.0, "4.0"),
    ],
)
# NumPy's functions on a torch tensor (the oracle's side) warn about torch's __array_wrap__.
@pytest.mark.filterwarnings("ignore:__array_wrap__:DeprecationWarning")
def test_traced_text_keeps_the_callables_order_of_operations(fn: Any, text: str | None) -> None:
    traced = trace_hamiltonian(fn, ("x1", "x2", "x3"))
    if text is not None:
        assert traced == text
    # Evaluated as text, the callable's own numbers on each state (same operations, same
    # order; x[0] names a coordinate on one state).
    x = torch.tensor(np.random.default_rng(3).uniform(0.5, 1.5, (9, 3)))
    want = torch.stack([torch.as_tensor(fn(row), dtype=torch.float64) for row in x])
    got = Expression(traced, ("x1", "x2", "x3")).evaluate(x, torch)
    if "exp(0.69" in traced or "tanh" in traced:
        # 2**x is rewritten as exp(x ln 2), and NumPy's sin and tanh are not torch's: a
        # last-bit difference.
        torch.testing.assert_close(got, want, rtol=1e-15, atol=0)
    else:
        assert torch.equal(got, want)


@pytest.mark.parametrize(
    ("fn", "match"),
    [
        (lambda x: abs(x[0]), "comparisons, abs"),
        (lambda x: x[0] if x[0] > 0 else x[1], "comparisons, abs"),
        (lambda x: x[0] if x[1] else x[2], "branches on the state"),
        (lambda x: torch.abs(x[..., 0]), "torch.abs is not in the grammar"),
        (lambda x: np.abs(x[..., 0]), "numpy.absolute is not in the grammar"),
        (lambda x: torch.where(x[0] > 0, x[0], x[1]), "comparisons"),
        (lambda x: x[..., 0] ** x[..., 1], "an exponent must be a number"),
        (lambda x: (-2.0) ** x[0], "not a real power"),
        (lambda x: x, "returns 3 numbers, not one"),
        (lambda x: x[5], "coordinate 5 does not exist"),
        (lambda x: x[0.5], "index the state by an integer"),
        (lambda x: x[..., 0, 1], "index the state by one coordinate"),
        (lambda x: x @ x, "failed on the traced state"),
        (lambda x: float("nan") * x[0], "constant nan is not finite"),
        (lambda x: 10**400 * x[0], "overflows float64"),
        (lambda x: math.sin(x[0]), "turns the state into a float"),
        (lambda x: x[0] + "a", "cannot combine the state with str"),
        (lambda x: x[0:2] + x, "of 2 and 3 numbers"),
        (lambda x: x + torch.ones(2), "3 numbers and 2"),
        (lambda x: torch.stack([x[0], x[1]]).sum(), "torch.stack is not in the grammar"),
        (lambda x: 1 / 0, "ZeroDivisionError"),
        ("not callable", "must be a string or a callable"),
    ],
)
def test_what_the_grammar_lacks_is_refused_in_one_error_naming_hamiltonian(
    fn: Any, match: str
) -> None:
    with pytest.raises(ExpressionError, match=match) as err:
        trace_hamiltonian(fn, ("x1", "x2", "x3"))
    assert str(err.value).startswith("hamiltonian")


def test_bounds_of_the_grammar_hold_for_traced_text() -> None:
    def deep(x: Any) -> Any:
        h = x[0]
        for _ in range(200):
            h = torch.sin(h)
        return h

    with pytest.raises(ValueError, match="hamiltonian"):
        pr.with_hamiltonian(pr.RigidBody(), deep)

    def long(x: Any) -> Any:
        h = x[0]
        for k in range(1200):
            h = h + (k + 0.123456789) * x[1]
        return h

    with pytest.raises(ValueError, match=f"characters as text, more than {MAX_CHARS}"):
        pr.with_hamiltonian(pr.RigidBody(), long)
    with pytest.raises(ValueError, match=r"exponent 100\.0 is outside"):
        pr.with_hamiltonian(pr.RigidBody(), lambda x: x[0] ** 100)


def test_names_are_the_components_own_where_the_grammar_reads_them() -> None:
    assert tracing_names(("u", "v", "r")) == ("u", "v", "r")
    assert tracing_names(("μ₁", "μ₂", "μ₃")) == ("μ₁", "μ₂", "μ₃")
    # A function's name, a repeated name or a non-identifier: the aliases x1 … xn.
    assert tracing_names(("sin", "v", "r")) == ("x1", "x2", "x3")
    assert tracing_names(("a", "a", "b")) == ("x1", "x2", "x3")
    assert tracing_names(("M 1", "M2", "M3")) == ("x1", "x2", "x3")
    with pytest.raises(ExpressionError, match="named x1 … xn in another order"):
        tracing_names(("x2", "x1", "x3"))
