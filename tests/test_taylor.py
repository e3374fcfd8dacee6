"""Tests for the exact Taylor expansion of the Hamilton–Jacobi generating function."""

import math
from fractions import Fraction

import numpy as np
import pytest

import poisson_rs.taylor as taylor_mod
from poisson_rs.taylor import (
    evaluate_terms,
    lie_taylor_coefficients,
    lie_taylor_terms,
    taylor_coefficients,
    taylor_terms,
)

INERTIA = (1.5, 2.0, 2.5)
F = Fraction


# ---------------------------------------------------------------------------------------------
# Exact test vectors (I = (1.5, 2, 2.5))
# ---------------------------------------------------------------------------------------------


def test_s1_is_minus_h() -> None:
    for chart in ("cayley", "exp"):
        s1 = taylor_coefficients(INERTIA, 1, chart)[0]
        assert s1 == {(2, 0, 0): F(-1, 3), (0, 2, 0): F(-1, 4), (0, 0, 2): F(-1, 5)}


def test_cayley_s3_exact() -> None:
    s3 = taylor_coefficients(INERTIA, 3)[2]
    assert s3 == {
        (4, 0, 0): F(-2, 81),
        (2, 2, 0): F(-71, 2160),
        (2, 0, 2): F(-17, 675),
        (0, 4, 0): F(-1, 96),
        (0, 2, 2): F(-11, 720),
        (0, 0, 4): F(-2, 375),
    }


def test_cayley_s5_known_term() -> None:
    s5 = taylor_coefficients(INERTIA, 5)[4]
    assert s5[(6, 0, 0)] == F(-19, 3645)
    # S_k is homogeneous of degree k + 1.
    assert all(sum(e) == 6 for e in s5)


def test_even_orders_vanish() -> None:
    # Both charts satisfy sou(−x, p) = tar(x, p), so the groupoid inversion x ↦ −x maps the
    # time-t bisection to the time-(−t) one: S(−t, p) = −S(t, p) and every even S_k is zero.
    cay = taylor_coefficients(INERTIA, 7, "cayley")
    assert [k for k in (2, 4, 6) if cay[k - 1]] == []
    assert taylor_coefficients(INERTIA, 2, "exp")[1] == {}


def test_exp_chart_vs_cayley() -> None:
    # sou_cayley − sou_exp = ¼ x(x·p) − c(|x|) x×(x×p) = O(|x|²) = O(t²), so H∘sou differs at
    # order t², i.e. S_1 and S_2 agree and S_3 is the first coefficient that may differ.
    cay = taylor_coefficients(INERTIA, 3, "cayley")
    exp = taylor_coefficients(INERTIA, 3, "exp")
    assert cay[:2] == exp[:2]
    assert cay[2] != exp[2]
    assert exp[2] == {(2, 2, 0): F(-1, 2160), (2, 0, 2): F(-1, 675), (0, 2, 2): F(-1, 3600)}


def test_exp_chart_axis_is_exact() -> None:
    # On a principal axis ∇S ∥ p, so x×p = 0 and the exp-chart source map is the identity:
    # S(t, p) = −t H(p) exactly there, i.e. no pure p_i^{k+1} monomial for k >= 2.
    exp = taylor_coefficients(INERTIA, 7, "exp")
    for s_k in exp[1:]:
        assert not any(sorted(e)[:2] == [0, 0] for e in s_k)


def test_coefficients_homogeneous_and_even() -> None:
    # The body is invariant under each reflection p_i ↦ −p_i, so only even exponents occur.
    for chart in ("cayley", "exp"):
        for k, s_k in enumerate(taylor_coefficients((1.0, 3.0, 7.0), 7, chart), start=1):
            for e in s_k:
                assert sum(e) == k + 1
                assert all(a % 2 == 0 for a in e)


# ---------------------------------------------------------------------------------------------
# Exchange format
# ---------------------------------------------------------------------------------------------


def test_terms_format() -> None:
    powers, coeffs = taylor_terms(INERTIA, 5)
    assert powers.dtype == np.int64 and coeffs.dtype == np.float64
    assert powers.ndim == 2 and powers.shape[1] == 4 and coeffs.shape == (powers.shape[0],)
    exact = taylor_coefficients(INERTIA, 5)
    assert powers.shape[0] == sum(len(s) for s in exact) == 3 + 6 + 10
    rows = [tuple(r) for r in powers.tolist()]
    assert rows == sorted(rows)
    assert np.all(coeffs != 0)
    for (k, a, b, c), v in zip(rows, coeffs, strict=True):
        assert v == float(exact[k - 1][(a, b, c)])


def test_evaluate_terms_matches_exact() -> None:
    rng = np.random.default_rng(42)
    powers, coeffs = taylor_terms(INERTIA, 5, "exp")
    exact = taylor_coefficients(INERTIA, 5, "exp")
    t = rng.uniform(-0.5, 0.5, size=4)
    p = rng.normal(size=(4, 3))
    got = evaluate_terms(powers, coeffs, t, p)
    assert got.shape == (4,)
    for n in range(4):
        tt, pp = F(t[n]), [F(x) for x in p[n]]
        want = sum(
            tt**k * c * pp[0] ** e[0] * pp[1] ** e[1] * pp[2] ** e[2]
            for k, s_k in enumerate(exact, start=1)
            for e, c in s_k.items()
        )
        assert got[n] == pytest.approx(float(want), rel=1e-12, abs=1e-15)
    # Broadcasting: scalar t against a batch of p, and a (2, 2) batch.
    assert evaluate_terms(powers, coeffs, 0.1, p).shape == (4,)
    assert evaluate_terms(powers, coeffs, t.reshape(2, 2), p.reshape(2, 2, 3)).shape == (2, 2)


# ---------------------------------------------------------------------------------------------
# Independent oracle: Hamilton–Jacobi residual of the truncated series
# ---------------------------------------------------------------------------------------------


def _hamiltonian(p: np.ndarray) -> np.ndarray:
    return 0.5 * np.sum(p**2 / np.asarray(INERTIA), axis=-1)


def _exp_c(theta: np.ndarray) -> np.ndarray:
    """c(θ) = (1 − (θ/2)cot(θ/2))/θ² in closed form, with its series below the cancellation."""
    small = theta < 1e-3
    safe = np.where(small, 1.0, theta)
    closed = (1 - (safe / 2) / np.tan(safe / 2)) / safe**2
    th2 = theta**2
    return np.where(small, 1 / 12 + th2 / 720 + th2**2 / 30240, closed)


def _source(x: np.ndarray, p: np.ndarray, chart: str) -> np.ndarray:
    xp = np.cross(x, p)
    if chart == "cayley":
        return p + 0.5 * xp + 0.25 * x * np.sum(x * p, axis=-1, keepdims=True)
    c = _exp_c(np.linalg.norm(x, axis=-1))[..., None]
    return p + 0.5 * xp + c * np.cross(x, xp)


def _derivative(powers: np.ndarray, coeffs: np.ndarray, col: int):
    """Terms of ∂/∂(variable col) of the polynomial (col 0 is t, cols 1..3 are p1..p3)."""
    keep = powers[:, col] > 0
    d_pow = powers[keep].copy()
    d_coef = coeffs[keep] * d_pow[:, col]
    d_pow[:, col] -= 1
    return d_pow, d_coef


def _hj_residual(order: int, chart: str, t: float, p: np.ndarray) -> np.ndarray:
    powers, coeffs = taylor_terms(INERTIA, order, chart)
    tt = np.full(p.shape[:-1], t)
    s_t = evaluate_terms(*_derivative(powers, coeffs, 0), tt, p)
    x = np.stack([evaluate_terms(*_derivative(powers, coeffs, i), tt, p) for i in (1, 2, 3)], -1)
    return s_t + _hamiltonian(_source(x, p, chart))


@pytest.mark.parametrize("chart", ["cayley", "exp"])
@pytest.mark.parametrize("order", [2, 3, 4, 5])
def test_hj_residual_order(chart: str, order: int) -> None:
    # By construction the residual's t^0..t^{K−1} coefficients vanish, and its t^K coefficient
    # is [t^K] H(sou(∇S)) = −(K+1) S_{K+1}, so generically R = O(t^K). In both charts the even
    # S_k vanish (S is odd in t), so for odd K the t^K term is absent and R = O(t^{K+1}), with
    # leading coefficient −(K+2) S_{K+2} ≠ 0. The fitted slope pins down which case holds.
    expected = order + 1 if order % 2 == 1 else order
    rng = np.random.default_rng(42)
    p = rng.normal(size=(5, 3))
    p *= 2.0 / np.linalg.norm(p, axis=-1, keepdims=True)
    ts = np.array([1e-1, 5e-2, 2.5e-2])
    if chart == "exp":
        # The exp chart is exact on the principal axes (and for an isotropic body), so its S_k,
        # k >= 3, are tiny (S_7(p) ~ 1e-6 at |p| = 2): at t = 2.5e-2 the K = 5 residual is at
        # float64 roundoff. Use a 4x larger grid, i.e. |p| ~ 8 at the same t, since
        # S(t, λp) = λ S(λt, p) by homogeneity.
        ts = 4 * ts
    res = np.stack([np.abs(_hj_residual(order, chart, t, p)) for t in ts])  # (3, 5)
    assert res.min() > 1e-13  # stay well above the roundoff floor so the fit is meaningful
    slopes = np.polyfit(np.log(ts), np.log(res), 1)[0]
    assert np.all(np.abs(slopes - expected) < 0.3), slopes


def test_hj_residual_at_zero_time_vanishes() -> None:
    # At t = 0: x = 0, sou = p, and ∂S/∂t = S_1 = −H.
    p = np.random.default_rng(42).normal(size=(3, 3))
    for chart in ("cayley", "exp"):
        np.testing.assert_allclose(_hj_residual(3, chart, 0.0, p), 0.0, atol=1e-14)


# ---------------------------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("inertia", "order", "chart", "match"),
    [
        ((1.0, 2.0), 3, "cayley", "inertia"),
        ((1.0, 2.0, 3.0, 4.0), 3, "cayley", "inertia"),
        ((1.0, -2.0, 3.0), 3, "cayley", "inertia"),
        ((1.0, 0.0, 3.0), 3, "cayley", "inertia"),
        ((1.0, float("nan"), 3.0), 3, "cayley", "inertia"),
        ((1.0, float("inf"), 3.0), 3, "cayley", "inertia"),
        (("a", "b", "c"), 3, "cayley", "inertia"),
        (None, 3, "cayley", "inertia"),
        (INERTIA, 0, "cayley", "order"),
        (INERTIA, 16, "cayley", "order"),
        (INERTIA, 2.0, "cayley", "order"),
        (INERTIA, True, "cayley", "order"),
        (INERTIA, 3, "euler", "chart"),
    ],
)
def test_bad_input(inertia, order, chart, match) -> None:
    with pytest.raises(ValueError, match=match):
        taylor_coefficients(inertia, order, chart)
    with pytest.raises(ValueError, match=match):
        taylor_terms(inertia, order, chart)


def test_accepts_ints_and_numpy() -> None:
    a = taylor_coefficients((1, 2, 3), np.int64(3))
    b = taylor_coefficients(np.array([1.0, 2.0, 3.0]), 3)
    assert a == b


# ---------------------------------------------------------------------------------------------
# Any Lie–Poisson system (exponential chart). Structure constants are built here, independently
# of poisson_rs.structures.lie_poisson: [e_i, e_j] = Σ_k c[i,j,k] e_k.
# ---------------------------------------------------------------------------------------------


def _so3() -> np.ndarray:
    c = np.zeros((3, 3, 3))
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        c[i, j, k], c[j, i, k] = 1.0, -1.0
    return c


def _se3() -> np.ndarray:
    """Basis R1..R3, T1..T3: [R_i,R_j] = ε_ijk R_k, [R_i,T_j] = ε_ijk T_k, [T_i,T_j] = 0."""
    eps, c = _so3(), np.zeros((6, 6, 6))
    c[:3, :3, :3] = eps
    c[:3, 3:, 3:] = eps
    c[3:, :3, 3:] = -eps.transpose(1, 0, 2)  # [T_j, R_i] = −[R_i, T_j]
    return c


def _sl2() -> np.ndarray:
    """Basis (h, e, f): [h,e] = 2e, [h,f] = −2f, [e,f] = h."""
    c = np.zeros((3, 3, 3))
    c[0, 1, 1], c[1, 0, 1] = 2.0, -2.0
    c[0, 2, 2], c[2, 0, 2] = -2.0, 2.0
    c[1, 2, 0], c[2, 1, 0] = 1.0, -1.0
    return c


def _unit(n: int, *idx: int) -> tuple[int, ...]:
    e = [0] * n
    for i in idx:
        e[i] += 1
    return tuple(e)


TOP_INERTIA = (1.0, 1.5, 2.0)
MGL = 0.981
# Heavy top, χ = (0, 0, 1): H = ½ Σ M_i²/I_i + mgl Γ_3 (not homogeneous).
HEAVY_TOP = {_unit(6, i, i): 0.5 / TOP_INERTIA[i] for i in range(3)} | {_unit(6, 5): MGL}
# sl(2,R): an indefinite quadratic with a cross term.
SL2_H = {(2, 0, 0): 0.5, (0, 1, 1): 1.0, (0, 2, 0): 0.3, (0, 0, 2): 0.2, (1, 1, 0): -0.4}
SYSTEMS = {"se3": (_se3(), HEAVY_TOP), "sl2": (_sl2(), SL2_H)}


def _random_h(n: int, seed: int) -> dict[tuple[int, ...], float]:
    """Seeded polynomial of degree <= 3 with a constant, linear, quadratic and cubic part."""
    rng = np.random.default_rng(seed)
    h: dict[tuple[int, ...], float] = {(0,) * n: float(rng.normal())}
    for i in range(n):
        h[_unit(n, i)] = float(rng.normal())
        for j in range(i, n):
            h[_unit(n, i, j)] = float(rng.normal())
    for _ in range(3):
        h[_unit(n, *rng.integers(0, n, size=3))] = float(rng.normal())
    return h


# A test-local exact polynomial algebra (dict exponent tuple → Fraction), independent of the
# packed-integer implementation in taylor.py.
Poly = dict[tuple[int, ...], Fraction]


def _padd(*ps: Poly) -> Poly:
    out: Poly = {}
    for q in ps:
        for e, c in q.items():
            out[e] = out.get(e, F(0)) + c
    return {e: c for e, c in out.items() if c}


def _pmul(a: Poly, b: Poly) -> Poly:
    out: Poly = {}
    for ea, ca in a.items():
        for eb, cb in b.items():
            e = tuple(x + y for x, y in zip(ea, eb, strict=True))
            out[e] = out.get(e, F(0)) + ca * cb
    return {e: c for e, c in out.items() if c}


def _pscale(a: Poly, s: Fraction) -> Poly:
    return {e: s * c for e, c in a.items() if s * c}


def _pdiff(a: Poly, i: int) -> Poly:
    out: Poly = {}
    for e, c in a.items():
        if e[i]:
            f = list(e)
            f[i] -= 1
            out[tuple(f)] = c * e[i]
    return out


def test_lie_so3_reproduces_rigid_body_exp_chart() -> None:
    # Fractions make H = ½ Σ p_i²/I_i exact (1/3 and 1/5 are not binary floats), so the two
    # independent recursions must agree to the last digit.
    h = {(2, 0, 0): F(1, 3), (0, 2, 0): F(1, 4), (0, 0, 2): F(1, 5)}
    assert lie_taylor_coefficients(_so3(), h, 7) == taylor_coefficients(INERTIA, 7, "exp")
    # Floats are converted bit for bit: 0.25 and 0.125 are exact binary fractions.
    hf = {(2, 0, 0): 0.25, (0, 2, 0): 0.125, (0, 0, 2): 0.125}
    assert lie_taylor_coefficients(_so3(), hf, 5) == taylor_coefficients((2, 4, 4), 5, "exp")


@pytest.mark.parametrize("name", ["se3", "sl2", "se3-cubic", "sl2-cubic"])
def test_lie_low_orders_analytic(name: str) -> None:
    # With x = Σ t^j ∇S_j and σ = sou(x, p) = p + t σ_1 + t² σ_2 + ..., S_1 = −H, X_1 = −∇H, so
    # A_1 = −L with (L v)_j = Σ_{i,k} c[i,j,k] ∂_iH v_k, and V = L p is the Lie–Poisson vector
    # field. σ_1 = B_1 A_1 p = V/2, so 2 S_2 = −∇H·V/2 = −½ Σ c[i,j,k] ∂_iH ∂_jH p_k = 0 by
    # antisymmetry. Then X_2 = 0, σ_2 = (B_2/2) A_1² p = L V/12 and
    # 3 S_3 = −(∇H·L V/12 + ½ Vᵀ ∇²H V/4), where ∇H·L v = 0 again: S_3 = −Vᵀ ∇²H V / 24.
    sys_name, _, cubic = name.partition("-")
    c, h = SYSTEMS[sys_name]
    n = c.shape[0]
    if cubic:
        h = _random_h(n, seed=42)
    s = lie_taylor_coefficients(c, h, 3)
    h_exact: Poly = {e: F(v) for e, v in h.items()}
    assert s[0] == {e: -v for e, v in sorted(h_exact.items())}
    assert s[1] == {}
    grad = [_pdiff(h_exact, i) for i in range(n)]
    p = [{_unit(n, i): F(1)} for i in range(n)]
    v = [
        _padd(*(_pscale(_pmul(grad[i], p[k]), F(c[i, j, k])) for i in range(n) for k in range(n)))
        for j in range(n)
    ]
    quad = _padd(
        *(_pmul(_pmul(v[a], _pdiff(grad[a], b)), v[b]) for a in range(n) for b in range(n))
    )
    assert quad  # the check has teeth: S_3 is not zero
    assert s[2] == dict(sorted(_pscale(quad, F(-1, 24)).items()))


@pytest.mark.parametrize("name", ["se3", "sl2", "se3-cubic", "sl2-cubic"])
def test_lie_even_orders_vanish(name: str) -> None:
    # sou(−x, p) = (ad_x/(1 − e^{−ad_x}))ᵀ p = tar(x, p): the groupoid inversion is x ↦ −x, and
    # it maps the time-t bisection to the time-(−t) one, so S is odd in t for any g* and any H.
    sys_name, _, cubic = name.partition("-")
    c, h = SYSTEMS[sys_name]
    order = 7
    if cubic:
        # A dense cubic H makes S_k of degree 2k + 1 in n variables: keep the exact work small.
        h, order = _random_h(c.shape[0], seed=7), 5
    s = lie_taylor_coefficients(c, h, order)
    assert [k for k in range(2, order + 1, 2) if s[k - 1]] == []
    assert all(s[k - 1] for k in range(1, order + 1, 2))


def test_lie_heavy_top_structure() -> None:
    # Scaling Γ ↦ λ²Γ, M ↦ λM is a Poisson automorphism of se(3)* (the bracket has weight −1)
    # under which H is quasi-homogeneous of weight 2, so every term of S_k has weight k + 1.
    # Γ = 0 is a Poisson subspace carrying the free rigid body, so the Γ-free part of S_k is the
    # rigid-body exp-chart S_k (exact Fractions make H exact there).
    c = _se3()
    s = lie_taylor_coefficients(c, HEAVY_TOP, 7)
    assert {sum(e[:3]) + 2 * sum(e[3:]) - k for k, s_k in enumerate(s, 1) for e in s_k} == {1}
    h = {_unit(6, i, i): F(1, 2) / F(TOP_INERTIA[i]) for i in range(3)} | {_unit(6, 5): F(1)}
    rigid = taylor_coefficients(TOP_INERTIA, 7, "exp")
    for s_k, r_k in zip(lie_taylor_coefficients(c, h, 7), rigid, strict=True):
        assert {e[:3]: v for e, v in s_k.items() if not any(e[3:])} == r_k


def test_lie_terms_format_and_evaluation() -> None:
    c, h = SYSTEMS["se3"]
    powers, coeffs = lie_taylor_terms(c, h, 5)
    exact = lie_taylor_coefficients(c, h, 5)
    assert powers.dtype == np.int64 and coeffs.dtype == np.float64
    assert powers.shape == (sum(len(s) for s in exact), 7) and coeffs.shape == (powers.shape[0],)
    rows = [tuple(r) for r in powers.tolist()]
    assert rows == sorted(rows)
    for (k, *e), val in zip(rows, coeffs, strict=True):
        assert val == float(exact[k - 1][tuple(e)])
    rng = np.random.default_rng(42)
    t, p = rng.uniform(-0.5, 0.5, size=4), rng.normal(size=(4, 6))
    got = evaluate_terms(powers, coeffs, t, p)
    assert got.shape == (4,)
    for m in range(4):
        tt, pp = F(t[m]), [F(x) for x in p[m]]
        want = sum(
            tt**k * v * math.prod(pi**a for pi, a in zip(pp, e, strict=True))
            for k, s_k in enumerate(exact, start=1)
            for e, v in s_k.items()
        )
        assert got[m] == pytest.approx(float(want), rel=1e-12, abs=1e-15)
    assert evaluate_terms(powers, coeffs, t.reshape(2, 2), p.reshape(2, 2, 6)).shape == (2, 2)
    with pytest.raises(ValueError, match="shape"):
        evaluate_terms(powers, coeffs, t, p[:, :3])
    with pytest.raises(ValueError, match="powers"):
        evaluate_terms(powers, coeffs[:-1], t, p)


def _bernoulli_weights(n_max: int) -> np.ndarray:
    """a_n = B_n/n! from z = (e^z − 1) Σ a_n zⁿ, i.e. Σ_{j<=n} a_j/(n − j + 1)! = δ_{n0}."""
    a = [1.0]
    for m in range(1, n_max + 1):
        a.append(-sum(a[j] / math.factorial(m - j + 1) for j in range(m)))
    return np.array(a)


def _lie_source(c: np.ndarray, x: np.ndarray, p: np.ndarray, terms: int = 40) -> np.ndarray:
    """sou(x, p) = Σ_n (B_n/n!) Aⁿ p, A = ad_xᵀ, summed as a plain matrix series in float64."""
    a_mat = np.einsum("ijk,...i->...jk", c, x)  # (A)_{jk} = Σ_i c[i,j,k] x_i, shape (..., n, n)
    out, v = p.copy(), p.copy()
    for w in _bernoulli_weights(terms)[1:]:
        v = np.einsum("...jk,...k->...j", a_mat, v)
        out = out + w * v
    return out


def _eval_poly(h: dict[tuple[int, ...], float], p: np.ndarray) -> np.ndarray:
    return sum(v * np.prod(p ** np.array(e), axis=-1) for e, v in h.items())


def _lie_hj_residual(name: str, order: int, t: float, p: np.ndarray) -> np.ndarray:
    c, h = SYSTEMS[name]
    n = c.shape[0]
    powers, coeffs = lie_taylor_terms(c, h, order)
    tt = np.full(p.shape[:-1], t)
    s_t = evaluate_terms(*_derivative(powers, coeffs, 0), tt, p)
    x = np.stack(
        [evaluate_terms(*_derivative(powers, coeffs, i), tt, p) for i in range(1, n + 1)], -1
    )
    return s_t + _eval_poly(h, _lie_source(c, x, p))


@pytest.mark.parametrize("name", ["se3", "sl2"])
@pytest.mark.parametrize("order", [2, 3, 4, 5])
def test_lie_hj_residual_order(name: str, order: int) -> None:
    # The residual of the truncated series is −(K+1) S_{K+1} t^K + O(t^{K+1}); S is odd in t,
    # so for odd K that term vanishes and the fitted slope is K + 1 instead.
    c, h = SYSTEMS[name]
    s = lie_taylor_coefficients(c, h, order + 2)
    expected = order if s[order] else order + 1
    assert s[expected]  # the leading residual coefficient, −(expected+1) S_{expected+1}, ≠ 0
    assert expected == order + order % 2
    rng = np.random.default_rng(42)
    p = rng.normal(size=(40, c.shape[0]))
    p *= 6.0 / np.linalg.norm(p, axis=-1, keepdims=True)
    # S_{expected+1} changes sign on g* (sl(2)'s H is indefinite): where it nearly vanishes the
    # next order dominates over this t range. Keep the 5 points where it is largest.
    lead = {(expected + 1, *e): float(v) for e, v in s[expected].items()}
    lead_p, lead_c = np.array(list(lead), dtype=np.int64), np.array(list(lead.values()))
    p = p[np.argsort(-np.abs(evaluate_terms(lead_p, lead_c, 1.0, p)))[:5]]
    ts = np.geomspace(1e-2, 1e-1, 5)
    res = np.stack([np.abs(_lie_hj_residual(name, order, t, p)) for t in ts])  # (5, 5)
    assert res.min() > 5e-13  # well above the roundoff floor, so the fit is meaningful
    slopes = np.polyfit(np.log(ts), np.log(res), 1)[0]
    assert np.all(np.abs(slopes - expected) < 0.3), slopes


def test_lie_numpy_source_matches_so3_chart() -> None:
    # The test-local series sou agrees with the closed-form exp chart of the rigid-body tests.
    rng = np.random.default_rng(42)
    x, p = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    np.testing.assert_allclose(_lie_source(_so3(), x, p), _source(x, p, "exp"), atol=1e-13)


_BAD_C = np.zeros((3, 3, 3))
_BAD_C[0, 1, 2] = 1.0  # not antisymmetric
_NOT_LIE = _so3() + 0.5 * np.abs(_so3())  # antisymmetric part broken too
_NO_JACOBI = _sl2()
_NO_JACOBI[0, 1, 1], _NO_JACOBI[1, 0, 1] = 3.0, -3.0  # [h,e] = 3e breaks Jacobi with [e,f] = h
_NAN_C = _so3()
_NAN_C[0, 1, 2] = np.nan
_SO3_H = {(2, 0, 0): 1.0}


@pytest.mark.parametrize(
    ("c", "h", "order", "match"),
    [
        (np.zeros((3, 3)), _SO3_H, 3, "shape"),
        (np.zeros((2, 3, 3)), _SO3_H, 3, "shape"),
        (np.zeros((0, 0, 0)), {(): 1.0}, 3, "shape"),
        ("abc", _SO3_H, 3, "structure_constants"),
        (_NAN_C, _SO3_H, 3, "finite"),
        (_BAD_C, _SO3_H, 3, "antisymmetric"),
        (_NOT_LIE, _SO3_H, 3, "antisymmetric"),
        (_NO_JACOBI, _SO3_H, 3, "Jacobi"),
        (_so3(), _SO3_H, 0, "order"),
        (_so3(), _SO3_H, 16, "order"),
        (_so3(), _SO3_H, 2.0, "order"),
        (_so3(), _SO3_H, True, "order"),
        (_so3(), [((2, 0, 0), 1.0)], 3, "mapping"),
        (_so3(), {(2, 0): 1.0}, 3, "length n = 3"),
        (_so3(), {(2, 0, 0, 0): 1.0}, 3, "length n = 3"),
        (_so3(), {2: 1.0}, 3, "length n = 3"),
        (_so3(), {(2, -1, 0): 1.0}, 3, "non-negative"),
        (_so3(), {(2.0, 0, 0): 1.0}, 3, "non-negative"),
        (_so3(), {(2, 0, 0): float("nan")}, 3, "finite"),
        (_so3(), {(2, 0, 0): float("inf")}, 3, "finite"),
        (_so3(), {(2, 0, 0): "a"}, 3, "real number"),
        (_so3(), {(2, 0, 0): True}, 3, "real number"),
    ],
)
def test_lie_bad_input(c, h, order, match) -> None:
    with pytest.raises(ValueError, match=match):
        lie_taylor_coefficients(c, h, order)
    with pytest.raises(ValueError, match=match):
        lie_taylor_terms(c, h, order)


def test_lie_work_budget(monkeypatch: pytest.MonkeyPatch) -> None:
    # A budget of this size is spent by S_5 of the heavy top but not by S_3: the error names
    # both the requested order and the largest one that fits, instead of running for minutes.
    monkeypatch.setattr(taylor_mod, "MAX_WORK", 2000)
    c, h = SYSTEMS["se3"]
    assert lie_taylor_coefficients(c, h, 3)
    with pytest.raises(ValueError, match=r"order 7 is too large .* S_\d .* use order <= \d"):
        lie_taylor_coefficients(c, h, 7)


def test_lie_trivial_cases() -> None:
    # Abelian algebra: sou = p, so S = −tH exactly. Zero Hamiltonian: S = 0.
    h = _random_h(4, seed=1)
    s = lie_taylor_coefficients(np.zeros((4, 4, 4)), h, 5)
    assert s[0] == {e: -F(v) for e, v in sorted(h.items())} and s[1:] == [{}] * 4
    assert lie_taylor_coefficients(_se3(), {}, 3) == [{}, {}, {}]
    assert lie_taylor_coefficients(_se3(), {(0,) * 6: 0.0}, 3) == [{}, {}, {}]


class _Stub:
    """Duck-typed stand-in for poisson_rs.structures.lie_poisson.LiePoissonSystem."""

    def __init__(self, c: np.ndarray, h: dict, inertia: tuple | None = None) -> None:
        self.algebra = type("Alg", (), {"c": c})()
        self.polynomial = type("Poly", (), {"terms": h})()
        if inertia is not None:
            self.inertia = inertia


def test_system_taylor_terms_dispatch() -> None:
    from poisson_rs.taylor import system_taylor_terms

    # so(3) with a diagonal quadratic H keeps the rigid-body recursion, Cayley chart included.
    body = _Stub(_so3(), {(2, 0, 0): 0.25, (0, 2, 0): 0.125, (0, 0, 2): 0.1}, inertia=INERTIA)
    for chart in ("cayley", "exp"):
        got, want = system_taylor_terms(body, 5, chart), taylor_terms(INERTIA, 5, chart)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    diag = _Stub(_so3(), {(2, 0, 0): 0.25, (0, 2, 0): 0.125, (0, 0, 2): 0.125})
    got, want = system_taylor_terms(diag, 5, "cayley"), taylor_terms((2, 4, 4), 5, "cayley")
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    top = _Stub(_se3(), HEAVY_TOP)
    got, want = system_taylor_terms(top, 3), lie_taylor_terms(_se3(), HEAVY_TOP, 3)
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    with pytest.raises(ValueError, match="only available for the rigid body"):
        system_taylor_terms(top, 3, "cayley")
    with pytest.raises(ValueError, match="chart"):
        system_taylor_terms(top, 3, "euler")
