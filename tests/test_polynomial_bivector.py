"""Polynomial bivectors: construction checks (antisymmetry, Jacobi naming the triple), the
order-n approximate realizations against the realization conditions (residual orders in |p|)
and against the exact so(3) groupoid (the Bernoulli series), and the Taylor-HJ integrator on a
cubic Nambu structure (fitted global order, Casimir drift per step, against DOP853)."""

from __future__ import annotations

import sys
from collections.abc import Iterator

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
    """max |{β^i, β^j} − π^{ij}(β)|, max |{α^i, α^j} + π^{ij}(α)|, max |{α^i, β^j}| and
    |C(β) − C(α)| at one (x, p), from sympy derivatives evaluated in NumPy."""
    beta, alpha, psym = structure.realization(order)
    xs = structure.x
    args = (*xs, *psym)

    def jac(f):
        jx = sympy.lambdify(args, [[sympy.diff(fi, v) for v in xs] for fi in f])(*x, *p)
        jp = sympy.lambdify(args, [[sympy.diff(fi, v) for v in psym] for fi in f])(*x, *p)
        return np.array(jx, dtype=float), np.array(jp, dtype=float)

    bx, bp = jac(beta)
    ax, ap = jac(alpha)
    bval = np.array(sympy.lambdify(args, beta)(*x, *p), dtype=float)
    aval = np.array(sympy.lambdify(args, alpha)(*x, *p), dtype=float)
    bb = bx @ bp.T - bp @ bx.T
    aa = ax @ ap.T - ap @ ax.T
    ab = ax @ bp.T - ap @ bx.T
    c = sympy.lambdify(xs, structure.casimir)
    return (
        np.abs(bb - structure(bval[None])[0]).max(),
        np.abs(aa + structure(aval[None])[0]).max(),
        np.abs(ab).max(),
        abs(c(*bval) - c(*aval)),
    )


@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_realization_residual_orders(order: int) -> None:
    """Measured slopes in |p| of {β, β} − π(β), {α, α} + π(α) and {α, β}: at least the order n
    (order 2 gives 3 for the first at this point); of C(β) − C(α): n + 1 for even n and n + 2
    for odd n (the defect is odd in p)."""
    structure = PolynomialBivector.nambu(CUBIC_C)
    rng = np.random.default_rng(5)
    x = rng.uniform(-1, 1, 3)
    direction = rng.normal(size=3)
    rows = [_conditions(structure, order, x, eps * direction) for eps in (0.04, 0.02)]
    slopes = np.log2(np.array(rows[0]) / np.array(rows[1]))
    assert (slopes[:3] > order - 0.2).all(), slopes
    assert slopes[:3].min() < order + 1.2, slopes  # not higher than claimed by luck of zeros
    assert abs(slopes[3] - (order + 1 + order % 2)) < 0.2, slopes


@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_alpha_beta_units(order: int) -> None:
    structure = PolynomialBivector.nambu(CUBIC_C)
    beta, alpha, p = structure.realization(order)
    zero = dict.fromkeys(p, 0)
    assert [b.subs(zero) for b in beta] == list(structure.x)
    assert [a.subs(zero) for a in alpha] == list(structure.x)


def test_second_order_term_is_the_closed_form() -> None:
    """The recursion's β_2 is (1/12)π^{lm}∂_lπ^{ij}p_m p_j, derived by hand."""
    structure = PolynomialBivector.nambu(CUBIC_C)
    terms, p = structure.realization_terms(2)
    x, pi = structure.x, structure.pi
    for i in range(3):
        closed = sympy.Rational(1, 12) * sum(
            pi[l_, m] * sympy.diff(pi[i, j], x[l_]) * p[m] * p[j]
            for l_ in range(3)
            for m in range(3)
            for j in range(3)
        )
        assert sympy.expand(terms[1][i] - closed) == 0


def test_linear_bracket_gives_the_exact_groupoid() -> None:
    """On so(3) (π p = p × x) the exact groupoid's source map is the Bernoulli series
    β = (1 + L/2 + L²/12 − L⁴/720 + …) x with L x = x × p; the recursion must reproduce it
    term by term, odd terms past the first vanishing."""
    structure = PolynomialBivector.nambu("(x1**2 + x2**2 + x3**2)/2")
    terms, p = structure.realization_terms(5)
    pv = sympy.Matrix(p)
    v = sympy.Matrix(structure.x)
    coefficients = [sympy.Rational(1, 2), sympy.Rational(1, 12), 0, sympy.Rational(-1, 720), 0]
    for k, coef in enumerate(coefficients):
        v = v.cross(pv)
        assert [sympy.expand(terms[k][i] - coef * v[i]) for i in range(3)] == [0, 0, 0], k + 1


def test_realization_order_is_checked() -> None:
    structure = PolynomialBivector.nambu(CUBIC_C)
    for bad in (0, 7, True, "3", 2.0):
        with pytest.raises(ValueError, match="realization order"):
            structure.realization(bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="realization order"):
        RealizationTaylorIntegrator(cubic(), 3, 9)
    from poisson_rs.structures.polynomial import matched_realization_order

    assert [matched_realization_order(m) for m in (1, 2, 3, 4, 5)] == [3, 3, 3, 5, 5]


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


@pytest.mark.parametrize(
    ("m", "n", "expected"), [(1, 2, 2), (2, 2, 2), (3, 2, 2), (3, 3, 4), (3, 4, 4), (5, 5, 6)]
)
def test_global_order(m: int, n: int, expected: int) -> None:
    """Order min(n, m) rounded up to even (the scheme is symmetric), and 2 for m = 1."""
    system = cubic()
    x0 = np.array([[0.3, 0.5, -0.4], [0.1, -0.6, 0.3]])
    ref = _reference(system, x0, 1.0)
    integ = RealizationTaylorIntegrator(system, m, n)
    assert integ.name == f"taylor{m}-realization{n}"
    steps = (4, 8) if expected == 6 else (10, 20)  # order 6 meets round-off by h = 1/16
    errs = [np.abs(pr.integrate(integ, x0, 1.0 / k, k)[:, -1] - ref).max() for k in steps]
    assert abs(np.log2(errs[0] / errs[1]) - expected) < 0.15, errs
    # S₂ = 0: π∇H·∇H = 0.
    if m >= 2:
        assert integ.s_terms[1] == 0


def test_default_realization_matches_the_taylor_order() -> None:
    integ = RealizationTaylorIntegrator(cubic(), 3)
    assert (integ.name, integ.realization_order) == ("taylor3-realization", 3)


@pytest.mark.parametrize(("n", "expected"), [(1, 3), (2, 3), (3, 5), (4, 5)])
def test_casimir_drift_per_step(n: int, expected: int) -> None:
    """C(β) − C(α) is odd in p and its |p| term vanishes (∇C·π = 0): Taylor m = 3 keeps C to
    O(h³) a step on the order-1 and order-2 realizations and to O(h⁵) on orders 3 and 4."""
    system = cubic()
    x0 = np.random.default_rng(0).uniform(-0.6, 0.6, (10, 3))
    integ = RealizationTaylorIntegrator(system, 3, n)
    hs = [0.4, 0.2, 0.1]
    drifts = []
    for h in hs:
        c = system.casimirs(pr.integrate(integ, x0, h, 1))
        drifts.append(np.abs(c[:, 1] - c[:, 0]).max())
    slope = np.polyfit(np.log(hs), np.log(drifts), 1)[0]
    assert abs(slope - expected) < 0.15, (slope, drifts)


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


@pytest.mark.parametrize(("m", "n"), [(1, 2), (3, 3), (5, 5)])
def test_rust_rollout_equals_the_numpy_step(m: int, n: int) -> None:
    """The core steps the same Newton bisection from the polynomial coefficients as the NumPy
    oracle does from the lambdified sympy expressions."""
    system = cubic()
    integ = RealizationTaylorIntegrator(system, m, n)
    x0 = np.random.default_rng(11).uniform(-0.7, 0.7, (13, 3))
    state, oracle = x0.copy(), [x0]
    for _ in range(15):
        state, ok = integ.step(state, 0.1)
        assert ok.all()
        oracle.append(state)
    traj, info = pr.integrate(integ, x0, 0.1, 15, return_info=True)
    np.testing.assert_allclose(traj, np.stack(oracle, 1), rtol=0, atol=1e-13)
    assert info.converged.all() and (info.newton_iterations > 0).all()


def test_rust_rollout_reports_a_failed_newton_solve() -> None:
    """A step far too large for Newton fails with a code, its later states NaN, the other
    trajectories unchanged."""
    integ = RealizationTaylorIntegrator(cubic(), 3, 3, max_iter=8)
    x0 = np.array([[0.3, 0.5, -0.4], [40.0, -30.0, 25.0]])
    traj, info = pr.integrate(integ, x0, 0.5, 4, return_info=True, on_failure="ignore")
    assert info.converged.tolist() == [True, False]
    assert info.failure_code[1] != 0 and np.isnan(traj[1, -1]).all()
    alone = pr.integrate(integ, x0[:1], 0.5, 4)
    assert traj[0].tobytes() == alone[0].tobytes()


def test_core_refuses_bad_term_tables() -> None:
    from poisson_rs import _core

    integ = RealizationTaylorIntegrator(cubic(), 1, 2)
    good = list(integ._tables)
    x0 = np.zeros((1, 3))

    def call(i: int, value: np.ndarray) -> None:
        args = list(good)
        args[i] = value
        _core.rollout_polynomial_realization(*args, x0, 0.1, 1)

    with pytest.raises(ValueError, match="sou exponents must have 6 columns"):
        call(2, good[2][:, :5].copy())
    with pytest.raises(ValueError, match="sou index"):
        call(0, np.full_like(good[0], 3))
    with pytest.raises(ValueError, match="must not be negative"):
        call(5, -good[5])
    with pytest.raises(ValueError, match="not finite"):
        call(6, np.full_like(good[6], np.nan))
    with pytest.raises(ValueError, match="tar exponents has"):
        call(5, good[5][:-1].copy())


def _no_sympy_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Makes any sympy parse or expansion raise: a refusal must come before them."""

    def work(*args: object, **kwargs: object) -> None:
        raise AssertionError("sympy ran on a polynomial that should have been refused")

    monkeypatch.setattr(sympy, "sympify", work)
    monkeypatch.setattr(sympy, "expand", work)


@pytest.fixture
def default_recursion_limit() -> Iterator[None]:
    """The interpreter's default recursion limit for one test: whether a 3000-term sum is
    "nested too deeply" for Python's parser depends on it, and torch.compile raises it (to 2000,
    run in the device-rollout tests before these); under a raised limit the sum parses and the
    degree and term bounds refuse it instead."""
    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(1000)
    yield
    sys.setrecursionlimit(limit)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("9**9**9**9", "exponent 387420489 of a constant exceeds"),
        ("(x1+x2+x3)**3000", "exponent 3000 of a variable"),
        ("((x1+x2+x3)**6)**3", r"degree 18 \(or more\) exceeds"),
        ("(x1+x2+x3+1)**12 * (x1+x2+x3+1)**12", "degree 24"),
        ("+".join(f"{k}*x1**{k % 13}*x2" for k in range(3000)), "nested too deeply|terms"),
        ("x1**2 + 1e400", "not finite"),
        ("exp(x1)", "not a polynomial"),
        ("x1**0.5", "exponents must be integer"),
        ("x1/x2", "only division by a constant"),
        ("x1^2", "not a polynomial"),
        ("__import__('os')", "not a polynomial"),
    ],
)
def test_hostile_polynomial_text_is_refused_before_sympy(
    monkeypatch: pytest.MonkeyPatch, default_recursion_limit: None, text: str, match: str
) -> None:
    """Every polynomial field (a bracket entry, H, a Nambu Casimir) is bounded from its syntax
    tree: degree <= MAX_DEGREE, terms and expansion work bounded, constants finite. The refusal
    names the field and comes before sympy parses or expands anything."""
    structure = PolynomialBivector.nambu(CUBIC_C)
    _no_sympy_work(monkeypatch)
    with pytest.raises(ValueError, match=f"^casimir: .*({match})"):
        PolynomialBivector.nambu(text)
    with pytest.raises(ValueError, match=f"^entry \\(0, 1\\): .*({match})"):
        PolynomialBivector(3, {(0, 1): text})
    with pytest.raises(ValueError, match=f"^hamiltonian: .*({match})"):
        PolynomialPoissonSystem(structure, text)


def test_model_metadata_polynomials_are_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    """A system dictionary (a model file's metadata) goes through the same bounds."""
    data = cubic().to_dict()
    _no_sympy_work(monkeypatch)
    with pytest.raises(ValueError, match=r"^casimir: .*exponent 3000"):
        PolynomialPoissonSystem.from_dict({**data, "casimir": "(x1+x2+x3)**3000"})
    with pytest.raises(ValueError, match=r"^entry \(0, 1\): .*exponent 387420489"):
        PolynomialPoissonSystem.from_dict(
            {**data, "casimir": None, "entries": [[0, 1, "9**9**9**9"]]}
        )


def test_a_realization_too_costly_is_refused_before_the_step(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The Nambu bracket of x1**12 + x2**2 + x3**2 is legal, but its order-3 realization (the
    least any Taylor-HJ uses) expands (x1 + b1)**11 with b1 of 7 terms: about 190,000 products,
    over a minute and growing past gigabytes with the HJ series. The step is estimated from
    the terms already built and refused, naming the Casimir, before sympy expands it."""
    structure = PolynomialBivector.nambu("x1**12 + x2**2 + x3**2")
    system = PolynomialPoissonSystem(structure, H)
    structure.realization_terms(2)
    _no_sympy_work(monkeypatch)
    with pytest.raises(ValueError, match=r"^casimir 'x1\*\*12 .*realization of order 3"):
        RealizationTaylorIntegrator(system, 1)


def test_a_taylor_hj_term_too_costly_is_refused_before_the_series(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """H = (x1 + x2 + x3)**6 on the cubic bracket: S_3 takes about a minute of sympy (measured
    58 s) and S_4 more; refused at S_3 from the sizes of β and S_1, S_2, naming H."""
    import poisson_rs.structures.polynomial as poly

    system = PolynomialPoissonSystem(PolynomialBivector.nambu(CUBIC_C), "(x1 + x2 + x3)**6")
    poly.hj_series(system, 2, 3)
    real = poly._series_compose
    calls: list[int] = []

    def counted(*args: object, **kwargs: object) -> object:
        calls.append(1)
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(poly, "_series_compose", counted)
    with pytest.raises(ValueError, match=r"^hamiltonian 'x1\*\*6 .*S_3 would cost"):
        poly.hj_series(system, 3, 3)
    # S_2 is recomputed (one composition per β component and one for H); S_3 never starts.
    assert len(calls) == 4


@pytest.mark.parametrize("scale", [1.0, 1e-5, 1e-100])
def test_jacobi_check_is_scale_invariant(scale: float) -> None:
    """The Jacobiator is measured against the size of its own terms (both scale as π²): a
    bracket that fails Jacobi fails at every scale; one that holds passes at every scale."""
    bad = {(0, 1): f"{scale}*x3**2", (1, 2): f"{scale}*x1", (0, 2): f"{scale}*x1*x2"}
    with pytest.raises(ValueError, match=r"Jacobi identity for the triple \(i, j, k\) = \(0, 1"):
        PolynomialBivector(3, bad)
    good = {(0, 1): f"{scale}*x1*x2", (0, 2): f"{2 * scale}*x1*x3", (1, 2): f"{-scale}*x2*x3"}
    PolynomialBivector(3, good)
    PolynomialBivector(3, {k: f"1e140*({v})" for k, v in good.items()})


@pytest.mark.parametrize(
    ("entries", "error", "match"),
    [
        ({(0, 1): float("nan")}, ValueError, r"^entry \(0, 1\): the constant nan"),
        ({(0, 1): np.inf}, ValueError, r"^entry \(0, 1\): the constant inf"),
        ({(0, 1): sympy.nan}, ValueError, r"^entry \(0, 1\): the constant nan"),
        ({(0, 1): "1e160*x1"}, ValueError, r"^entry \(0, 1\): the constant 1e\+160 .* 1e\+150"),
        ({(0, 1): b"x1"}, TypeError, r"^entry \(0, 1\) must be a polynomial .* got bytes"),
        ({(0, 1): True}, TypeError, r"^entry \(0, 1\) must be a polynomial"),
        ({(0,): "x1"}, TypeError, r"^entry key \(0,\) must be a pair"),
        ({"01": "x1"}, TypeError, r"^entry key '01' must be a pair"),
        ({(0.0, 1): "x1"}, TypeError, r"^entry key \(0.0, 1\) must be a pair"),
        ({(0, 1): "x3"}, ValueError, r"^entry \(0, 1\): .*unknown name 'x3'"),
    ],
)
def test_bad_entries_get_one_clear_error(
    entries: dict[object, object], error: type[Exception], match: str
) -> None:
    with pytest.raises(error, match=match):
        PolynomialBivector(2, entries)  # type: ignore[arg-type]


def test_nambu_refuses_a_foreign_or_constant_casimir() -> None:
    """x4 is not a variable on R³ (it used to become a free symbol and the zero bracket), and a
    constant Casimir has the zero bracket."""
    with pytest.raises(ValueError, match=r"^casimir: .*unknown name 'x4'"):
        PolynomialBivector.nambu("x4**2")
    with pytest.raises(ValueError, match=r"^casimir: .*unknown symbol 'y'"):
        PolynomialBivector.nambu(sympy.Symbol("y") ** 2)
    # The caller's own symbols named x1, x2, x3 (not declared real) are the variables.
    x1, x2, x3 = sympy.symbols("x1 x2 x3")
    plain = PolynomialBivector.nambu(x1**2 + x2**2 + x3**2)
    assert plain.pi == PolynomialBivector.nambu("x1**2 + x2**2 + x3**2").pi
    with pytest.raises(ValueError, match="casimir '3' is constant"):
        PolynomialBivector.nambu("3")
    with pytest.raises(ValueError, match=r"^hamiltonian: .*unknown name 'x4'"):
        PolynomialPoissonSystem(PolynomialBivector.nambu(CUBIC_C), "x4**2")


def test_system_equality_follows_to_dict() -> None:
    """Equal systems (the same bracket and H, whatever their names or how H was written) are
    equal and hash alike, so a model trained on a scene's system is accepted for that scene."""
    import pickle

    system = cubic()
    same = PolynomialPoissonSystem(
        PolynomialBivector.nambu(CUBIC_C), "x3**2/4 + x2**2/3 + x1**2/2", name="other name"
    )
    assert same == system and hash(same) == hash(system) and not same != system
    again = PolynomialPoissonSystem.from_dict(system.to_dict())
    assert again == system and hash(again) == hash(system)
    assert pickle.loads(pickle.dumps(system)) == system
    assert {system: 1}[again] == 1
    # The scene's system (demo, select and stability compare it with a model's by !=).
    from pathlib import Path

    from poisson_rs.scenes import load_scene

    scene = load_scene(Path(__file__).resolve().parents[1] / "scenes" / "nambu_cubic.toml")
    assert not scene.system != system
    assert system != PolynomialPoissonSystem(PolynomialBivector.nambu(CUBIC_C), "x1**2/2")
    assert system != PolynomialPoissonSystem(PolynomialBivector.nambu("x1**2 + x2**2"), H)
    assert system != "not a system"
    # Irrational coefficients become the floats their text shows, so the text round-trips.
    x1, x2, x3 = system.structure.x
    irrational = PolynomialPoissonSystem(
        PolynomialBivector.nambu(sympy.sqrt(2) * x1**2 + sympy.pi * x2**2 + x3**2), H
    )
    assert PolynomialPoissonSystem.from_dict(irrational.to_dict()) == irrational
    assert pickle.loads(pickle.dumps(irrational)) == irrational
