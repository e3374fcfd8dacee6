"""Polynomial bivectors: construction checks (antisymmetry, Jacobi naming the triple), the
order-1/2 approximate realizations against the realization conditions (residual orders in |p|),
and the Taylor-HJ integrator on a cubic Nambu structure (fitted global order, Casimir drift per
step O(h³), against DOP853)."""

from __future__ import annotations

import numpy as np
import pytest
import sympy
from scipy.integrate import solve_ivp

import poisson_rs as pr
from poisson_rs.structures.polynomial import (
    PolynomialBivector,
    PolynomialPoissonSystem,
    RealizationTaylorIntegrator,
)

CUBIC_C = "x1**2/2 + x2**2/2 + x3**2/2 + x1**3/3"
H = "x1**2/2 + x2**2/3 + x3**2/4"


def cubic() -> PolynomialPoissonSystem:
    return PolynomialPoissonSystem(PolynomialBivector.nambu(CUBIC_C), H)


def test_jacobi_failure_names_the_triple() -> None:
    with pytest.raises(
        ValueError, match=r"Jacobi identity for the triple \(i, j, k\) = \(0, 1, 2\)"
    ):
        PolynomialBivector(3, {(0, 1): "x3**2", (1, 2): "x1", (0, 2): "x1*x2"})
    with pytest.raises(ValueError, match="antisymmetric"):
        PolynomialBivector(2, {(0, 1): "x1", (1, 0): "x1"})
    with pytest.raises(ValueError, match="not a polynomial"):
        PolynomialBivector(2, {(0, 1): "exp(x1)"})
    # Quadratic log-canonical and a 4D Lie–Poisson-like bracket pass.
    PolynomialBivector(3, {(0, 1): "x1*x2", (0, 2): "x1*x3", (1, 2): "x2*x3"})


def test_nambu_of_the_sphere_is_so3() -> None:
    """C = |x|² gives π^{ij} = 2 ε_ijk x_k."""
    b = PolynomialBivector.nambu("x1**2 + x2**2 + x3**2")
    x1, x2, x3 = b.x
    assert b.pi == sympy.Matrix([[0, 2 * x3, -2 * x2], [-2 * x3, 0, 2 * x1], [2 * x2, -2 * x1, 0]])


def _conditions(structure: PolynomialBivector, order: int, x: np.ndarray, p: np.ndarray):
    """max |{β^i, β^j} − π^{ij}(β)|, max |{α^i, β^j}| and |C(β) − C(α)| at one (x, p)."""
    beta, alpha, psym = structure.realization(order)
    xs = structure.x
    sub = {**dict(zip(xs, x, strict=True)), **dict(zip(psym, p, strict=True))}

    def jac(f):
        jx = np.array([[float(sympy.diff(fi, v).subs(sub)) for v in xs] for fi in f])
        jp = np.array([[float(sympy.diff(fi, v).subs(sub)) for v in psym] for fi in f])
        return jx, jp

    bx, bp = jac(beta)
    ax, ap = jac(alpha)
    bval = np.array([float(b.subs(sub)) for b in beta])
    aval = np.array([float(a.subs(sub)) for a in alpha])
    bb = bx @ bp.T - bp @ bx.T
    ab = ax @ bp.T - ap @ bx.T
    pi_b = structure(bval[None])[0]
    c = sympy.lambdify(xs, structure.casimir)
    return np.abs(bb - pi_b).max(), np.abs(ab).max(), abs(c(*bval) - c(*aval))


@pytest.mark.parametrize(("order", "expected"), [(1, (1.0, 1.0, 3.0)), (2, (3.0, 2.0, 3.0))])
def test_realization_residual_orders(order: int, expected: tuple[float, float, float]) -> None:
    """Measured slopes in |p| of ({β, β} − π(β), {α, β}, C(β) − C(α)): order 1 gives
    (1, 1, 3); order 2 gives (3, 2, 3): {β^i, β^j} − π^{ij}(β) shrinks even faster than the
    stated |p|², {α^i, β^j} as |p|²."""
    structure = PolynomialBivector.nambu(CUBIC_C)
    rng = np.random.default_rng(5)
    x = rng.uniform(-1, 1, 3)
    direction = rng.normal(size=3)
    rows = [_conditions(structure, order, x, eps * direction) for eps in (0.02, 0.01)]
    slopes = np.log2(np.array(rows[0]) / np.array(rows[1]))
    np.testing.assert_allclose(slopes, expected, atol=0.2)


def test_alpha_beta_units() -> None:
    structure = PolynomialBivector.nambu(CUBIC_C)
    beta, alpha, p = structure.realization(2)
    zero = dict.fromkeys(p, 0)
    assert [b.subs(zero) for b in beta] == list(structure.x)
    assert [a.subs(zero) for a in alpha] == list(structure.x)


def _reference(system: PolynomialPoissonSystem, x0: np.ndarray, t: float) -> np.ndarray:
    return np.array(
        [
            solve_ivp(
                lambda _t, y: system.vector_field(y[None])[0],
                (0, t),
                y,
                method="DOP853",
                rtol=1e-13,
                atol=1e-13,
            ).y[:, -1]
            for y in x0
        ]
    )


@pytest.mark.parametrize("m", [1, 2, 3])
def test_global_order_is_two(m: int) -> None:
    """Order min(2, m) on the order-2 realization, and 2 for m = 1 (S₂ = 0)."""
    system = cubic()
    x0 = np.array([[0.3, 0.5, -0.4], [0.1, -0.6, 0.3]])
    ref = _reference(system, x0, 1.0)
    integ = RealizationTaylorIntegrator(system, m)
    errs = [np.abs(pr.integrate(integ, x0, 1.0 / n, n)[:, -1] - ref).max() for n in (10, 20)]
    assert abs(np.log2(errs[0] / errs[1]) - 2.0) < 0.1, errs
    # S₂ = 0: π∇H·∇H = 0.
    if m >= 2:
        assert integ.s_terms[1] == 0


@pytest.mark.parametrize("realization_order", [1, 2])
def test_casimir_drift_per_step_is_third_order(realization_order: int) -> None:
    """C(β) − C(α) is odd in p and its |p| term vanishes (∇C·π = 0), so both the order-1 and
    the order-2 realization keep C to O(h³) a step."""
    system = cubic()
    x0 = np.random.default_rng(0).uniform(-0.6, 0.6, (10, 3))
    integ = RealizationTaylorIntegrator(system, 3, realization_order)
    hs = [0.2, 0.1, 0.05]
    drifts = []
    for h in hs:
        c = system.casimirs(pr.integrate(integ, x0, h, 1))
        drifts.append(np.abs(c[:, 1] - c[:, 0]).max())
    slope = np.polyfit(np.log(hs), np.log(drifts), 1)[0]
    assert abs(slope - 3.0) < 0.1, (slope, drifts)


def test_system_round_trip_and_interface() -> None:
    system = cubic()
    again = PolynomialPoissonSystem.from_dict(system.to_dict())
    x = np.array([[0.3, 0.5, -0.4]])
    np.testing.assert_allclose(again.vector_field(x), system.vector_field(x))
    assert system.component_names == ("x1", "x2", "x3")
    # The vector field is ∇H × ∇C (x1 component checked by hand at x).
    x1, x2, x3 = x[0]
    grad_h = np.array([x1, 2 * x2 / 3, x3 / 2])
    grad_c = np.array([x1 + x1**2, x2, x3])
    np.testing.assert_allclose(system.vector_field(x)[0], np.cross(grad_h, grad_c), rtol=1e-14)
