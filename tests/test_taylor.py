"""Tests for the exact Taylor expansion of the Hamilton–Jacobi generating function."""

from fractions import Fraction

import numpy as np
import pytest

from poisson_rs.taylor import evaluate_terms, taylor_coefficients, taylor_terms

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
