"""Log-canonical structures π_ij = c_ij x_i x_j (Lotka–Volterra): the exact groupoid against the
realization conditions (torch autograd brackets), the Hamilton–Jacobi series, the Rust step
against a NumPy Newton oracle, fitted orders against DOP853, Casimirs, bounded energy and the
positive orthant."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

import poisson_rs as pr
from poisson_rs.realizations import log_canonical as lc

PNN_C = [[0.0, 1.0], [-1.0, 0.0]]
#: A 3D structure with the Casimir x1 x3 / x2 (c k = 0 for k = (1, -1, 1)).
C3 = [[0.0, 1.0, 1.0], [-1.0, 0.0, 1.0], [-1.0, -1.0, 0.0]]


def pnn() -> pr.LogCanonicalSystem:
    return pr.lotka_volterra(PNN_C, [1.0, 2.0])


def lv3() -> pr.LogCanonicalSystem:
    return pr.lotka_volterra(C3, [1.0, 2.0, 1.0])


def _random_c(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return a - a.T


def _jacobians(f, x: torch.Tensor, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    jx, jp = torch.autograd.functional.jacobian(f, (x, p))
    return jx, jp


@pytest.mark.parametrize("n", [2, 3, 4])
def test_realization_conditions(n: int) -> None:
    """{β^i, β^j} = π^{ij}(β), {α^i, α^j} = −π^{ij}(α), {α^i, β^j} = 0 for the canonical bracket
    {x^i, p_j} = δ, by autograd at random points and momenta; α(x, 0) = β(x, 0) = x."""
    rng = np.random.default_rng(20 + n)
    c = _random_c(rng, n)
    structure = pr.LogCanonical(c)
    for _ in range(5):
        x = torch.tensor(rng.uniform(0.3, 2.0, n), dtype=torch.float64)
        p = torch.tensor(rng.normal(scale=0.5, size=n), dtype=torch.float64)
        ax, ap = _jacobians(lambda x, p: lc.alpha(c, x, p), x, p)
        bx, bp = _jacobians(lambda x, p: lc.beta(c, x, p), x, p)
        b = lc.beta(c, x, p)
        a = lc.alpha(c, x, p)
        bb = bx @ bp.T - bp @ bx.T
        aa = ax @ ap.T - ap @ ax.T
        ab = ax @ bp.T - ap @ bx.T
        torch.testing.assert_close(bb, structure.bivector(b), rtol=0, atol=1e-12)
        torch.testing.assert_close(aa, -structure.bivector(a), rtol=0, atol=1e-12)
        torch.testing.assert_close(ab, torch.zeros(n, n, dtype=torch.float64), rtol=0, atol=1e-12)
        zero = torch.zeros(n, dtype=torch.float64)
        assert torch.equal(lc.alpha(c, x, zero), x) and torch.equal(lc.beta(c, x, zero), x)
        # The log form is the same map: ln β(x, p) = β_log(ln x, x ∘ p).
        torch.testing.assert_close(torch.log(b), lc.beta_log(c, torch.log(x), x * p))
        torch.testing.assert_close(torch.log(a), lc.alpha_log(c, torch.log(x), x * p))


def test_taylor_terms() -> None:
    """S_1 = −H (its polynomial part), the even terms vanish (π∇H·∇H = 0), and the truncated S
    solves ∂S/∂t + H(β(q, ∇S)) = 0 to O(t^{m+1}) (autograd, independent of the series)."""
    system = lv3()
    terms = lc.taylor_terms(system, 5)
    assert {e: float(v) for e, v in terms[0].items()} == {
        (1, 0, 0): -1.0,
        (0, 1, 0): -1.0,
        (0, 0, 1): -1.0,
    }
    assert terms[1] == {} and terms[3] == {}
    rng = np.random.default_rng(3)
    q = torch.tensor(rng.normal(scale=0.3, size=(4, 3)), dtype=torch.float64)
    b = torch.tensor(system.log_hamiltonian.b)
    for m in (1, 3, 5):
        tp, ex, co = (torch.as_tensor(a) for a in lc.taylor_arrays(system, m))
        residuals = []
        for t0 in (0.04, 0.02):
            t = torch.full((len(q),), t0, dtype=torch.float64, requires_grad=True)
            qq = q.clone().requires_grad_(True)
            powers = t[:, None] ** tp.double()
            s = (co * powers * torch.exp(qq @ ex.double().T)).sum(-1) + t * (qq @ b)
            s_t, s_q = torch.autograd.grad(s.sum(), (t, qq))
            r = s_t + system.log_hamiltonian.in_log(lc.beta_log(system.c, q, s_q))
            residuals.append(float(r.abs().max()))
        # Residual O(t^{m+1}) (m odd: S_{m+1} = 0, so O(t^{m+1}) with the next odd term).
        slope = np.log2(residuals[0] / residuals[1])
        assert slope > m + 0.8, (m, residuals)


def test_rust_step_matches_numpy_oracle() -> None:
    rng = np.random.default_rng(7)
    for system in (pnn(), lv3()):
        x0 = rng.uniform(0.5, 2.0, size=(6, system.dim))
        for m in (1, 3, 5):
            arrays = lc.taylor_arrays(system, m)
            expected = lc.numpy_step(system, arrays, np.log(x0), 0.1)
            got = pr.integrate(pr.log_canonical_taylor(system, m), x0, 0.1, 1)[:, 1]
            np.testing.assert_allclose(np.log(got), expected, rtol=0, atol=1e-13)


def _fitted_order(make, system, x0: np.ndarray, t_end: float = 2.0) -> float:
    ref = pr.reference_solution(system, x0, [t_end])[:, -1]
    errs, hs = [], []
    for n in (10, 20, 40):
        traj = pr.integrate(make(), x0, t_end / n, n)
        errs.append(np.abs(traj[:, -1] - ref).max())
        hs.append(t_end / n)
    return float(np.polyfit(np.log(hs), np.log(errs), 1)[0])


@pytest.mark.parametrize(
    ("kind", "arg", "expected"),
    [
        ("taylor", 1, 2.0),
        ("taylor", 3, 4.0),
        ("taylor", 5, 6.0),
        ("classical", "log_splitting", 2.0),
        ("classical", "log_splitting4", 4.0),
        ("classical", "rk4", 4.0),
        ("classical", "midpoint", 2.0),
    ],
)
def test_fitted_orders(kind: str, arg: object, expected: float) -> None:
    """Taylor-HJ of odd order m has order m + 1; the splittings 2 and 4; against DOP853."""
    system = pnn()
    x0 = np.array([[1.0, 0.8], [1.0, 1.2]])
    if kind == "taylor":

        def make():
            return pr.log_canonical_taylor(system, arg)
    else:

        def make():
            return pr.log_canonical_classical(system, arg)

    order = _fitted_order(make, system, x0)
    assert abs(order - expected) < 0.2, order


def test_casimir_kept_over_1e4_steps() -> None:
    system = lv3()
    assert system.structure.casimir_vectors.tolist() == [[1, -1, 1]]
    x0 = np.array([[1.2, 0.7, 1.6], [0.5, 1.5, 0.9]])
    c0 = system.casimirs(x0)
    for stepper in (
        pr.log_canonical_taylor(system, 1),
        pr.log_canonical_taylor(system, 3),
        pr.log_canonical_classical(system, "log_splitting"),
        pr.log_canonical_classical(system, "log_splitting4"),
    ):
        traj = pr.integrate(stepper, x0, 0.1, 10_000, every=10)
        drift = np.abs(system.casimirs(traj) - c0[:, None, :]).max()
        assert drift <= 1e-12 * np.abs(c0).max(), (stepper, drift)
    # RK4 is not Poisson: its Casimir drifts far more (the check is not vacuous).
    traj = pr.integrate(pr.log_canonical_classical(system, "rk4"), x0, 0.1, 10_000, every=10)
    assert np.abs(system.casimirs(traj) - c0[:, None, :]).max() > 1e-8


def test_casimir_is_a_random_walk_of_round_off_at_small_steps() -> None:
    """A Taylor step returns q_k − c∇S(q), not q − ½c∇S(q): equal at Newton's solution, but the
    second carries the rounding of Newton's last iterate into k·q, with the same sign from step
    to step (1.5e-12 over these 10⁵ steps of h = 0.025; 3e-14 the first way)."""
    system = lv3()
    rng = np.random.default_rng(42)
    x0 = np.exp(rng.uniform(-0.4, 0.4, (8, 3))) * np.array([1.0, 2.0, 1.0])
    c0 = system.casimirs(x0)
    for order in (3, 5):
        traj = pr.integrate(pr.log_canonical_taylor(system, order), x0, 0.025, 100_000, every=1000)
        drift = np.abs(system.casimirs(traj) - c0[:, None, :]).max()
        assert drift < 2e-13, (order, drift)


def test_energy_bounded_over_1e5_steps() -> None:
    """No drift: the largest energy error of the second half of 10⁵ steps is no larger than
    that of the first half (to 10%), for Taylor m = 1 on the 3D system with a Casimir."""
    system = lv3()
    x0 = np.array([1.2, 0.7, 1.6])
    traj = pr.integrate(pr.log_canonical_taylor(system, 1), x0, 0.1, 100_000, every=10)
    err = np.abs(system.hamiltonian(traj) - system.hamiltonian(x0))
    half = len(err) // 2
    assert err[half:].max() <= 1.1 * err[:half].max()
    assert err.max() < 1e-2


def test_casimirs_none_for_invertible_c() -> None:
    assert pnn().casimirs([1.0, 1.0]) is None
    assert pnn().structure.casimir_vectors.shape == (0, 2)
    k = pr.LogCanonical([[0, 2, 0, 0], [-2, 0, 0, 0], [0, 0, 0, 3], [0, 0, -3, 0]])
    assert k.casimir_vectors.shape == (0, 4)
    k = pr.LogCanonical([[0, 0.5, -1.0], [-0.5, 0, 2.0], [1.0, -2.0, 0]])
    (row,) = k.casimir_vectors
    np.testing.assert_allclose(k.c @ row, 0.0, atol=1e-15)


def test_orthant_and_bad_input() -> None:
    system = pnn()
    with pytest.raises(ValueError, match="positive orthant"):
        pr.integrate(pr.log_canonical_taylor(system, 3), [1.0, -0.5], 0.1, 10)
    with pytest.raises(ValueError, match="positive orthant"):
        pr.integrate(pr.log_canonical_classical(system, "rk4"), [[1.0, 1.0], [0.0, 1.0]], 0.1, 1)
    with pytest.raises(ValueError, match="positive orthant"):
        system.hamiltonian([1.0, 0.0])
    with pytest.raises(ValueError, match="antisymmetric"):
        pr.lotka_volterra([[0, 1], [1, 0]], [1, 1])
    with pytest.raises(ValueError, match="b must have 2"):
        pr.lotka_volterra(PNN_C, [1, 2, 3])
    with pytest.raises(ValueError, match="unknown classical"):
        pr.log_canonical_classical(system, "splitting")
    with pytest.raises(ValueError, match="order"):
        pr.log_canonical_taylor(system, 0)


def test_leaving_the_orthant_is_a_failure_code() -> None:
    """RK4 with a step far too large jumps out of the orthant: failure code 5, NaN after it."""
    system = pnn()
    traj, info = pr.integrate(
        pr.log_canonical_classical(system, "rk4"),
        [1.0, 3.0],
        2.0,
        5,
        return_info=True,
        on_failure="ignore",
    )
    assert not info.converged[0] and info.failure_code[0] == 5
    k = int(info.failed_step[0])
    assert np.isnan(traj[k + 1 :]).all() and np.isfinite(traj[: k + 1]).all()
    with pytest.warns(RuntimeWarning, match="left the domain"):
        pr.integrate(pr.log_canonical_classical(system, "rk4"), [1.0, 3.0], 2.0, 5)


def test_taylor_step_that_overflows_is_a_failure() -> None:
    """A state so large that e^q overflows within a step stops with a failure code and NaN,
    never a silent inf."""
    system = pnn()
    traj, info = pr.integrate(
        pr.log_canonical_taylor(system, 3),
        [[1e300, 1.0], [1.0, 0.8]],
        0.1,
        3,
        return_info=True,
        on_failure="ignore",
    )
    assert not info.converged[0] and info.failure_code[0] != 0
    assert np.isnan(traj[0, 1:]).all()
    assert info.converged[1] and np.isfinite(traj[1]).all()


def test_round_trips() -> None:
    system = lv3()
    again = pr.LogCanonicalSystem.from_dict(system.to_dict())
    assert again == system and hash(again) == hash(system)
    assert pickle.loads(pickle.dumps(system)) == system
    x0 = np.array([1.2, 0.7, 1.6])
    for stepper in (pr.log_canonical_taylor(system, 3), pr.log_canonical_classical(system, "rk4")):
        clone = pickle.loads(pickle.dumps(stepper))
        np.testing.assert_array_equal(
            pr.integrate(clone, x0, 0.1, 20), pr.integrate(stepper, x0, 0.1, 20)
        )
    assert system.component_names == ("x₁", "x₂", "x₃")
    assert pnn().component_names == ("u", "v")


def test_vector_field_is_pnn() -> None:
    """u̇ = u(v − 2), v̇ = v(1 − u)."""
    x = np.array([[1.3, 0.4], [0.2, 2.5]])
    u, v = x.T
    np.testing.assert_allclose(
        pnn().vector_field(x), np.stack([u * (v - 2), v * (1 - u)], -1), rtol=1e-15
    )


@pytest.mark.parametrize(
    ("c", "b", "error", "match"),
    [
        ([[0.0]], [1.0], ValueError, r"^c must be a square .* 2 <= n"),
        ([[0, 1e300], [-1e300, 0]], [1, 2], ValueError, r"^c\[0, 1\] = 1e\+300 exceeds 1e\+15"),
        ([[0, 1e16], [-1e16, 0]], [1, 2], ValueError, r"^c\[0, 1\] = 1e\+16 exceeds"),
        (PNN_C, [1e300, 2], ValueError, r"^b\[0\] = 1e\+300 exceeds 1e\+15"),
        (PNN_C, [1, -1e16], ValueError, r"^b\[1\] = -1e\+16 exceeds"),
        (PNN_C, [1, np.nan], ValueError, "^b holds NaN"),
        (PNN_C, [b"1", 2], TypeError, "^b must be an array of real numbers"),
    ],
)
def test_degenerate_and_huge_constructor_input_is_named(
    c: object, b: object, error: type[Exception], match: str
) -> None:
    """One species (c = [[0]]) used to reach sympy's ilcm with one argument (TypeError), and c
    or b = 1e300 overflowed in the Taylor terms (OverflowError): each is now one error naming
    the field."""
    with pytest.raises(error, match=match):
        pr.lotka_volterra(c, b)


def test_largest_magnitudes_keep_the_taylor_terms_finite() -> None:
    """At the bound (|c|, |b| = 1e15) the exact Taylor terms convert to finite float64 through
    order 10 (1e150 overflowed at order 3)."""
    system = pr.lotka_volterra([[0, 1e15], [-1e15, 0]], [1e15, -1e15])
    for order in (3, 10):
        assert np.isfinite(lc.taylor_arrays(system, order)[2]).all()
    with pytest.raises(ValueError, match=r"Hamiltonian coefficient of \(1, 0\) = 2e\+15 exceeds"):
        pr.LogPolynomial({(1, 0): 2e15}, [0.0, 0.0])


#: A 5-D bracket with decimal entries: its exact null vector has integers far beyond int64.
C5 = [
    [0.0, 1.0, -0.5, 0.3, 0.2],
    [-1.0, 0.0, 0.7, -0.4, 0.1],
    [0.5, -0.7, 0.0, 0.6, -0.3],
    [-0.3, 0.4, -0.6, 0.0, 0.9],
    [-0.2, -0.1, 0.3, -0.9, 0.0],
]


def test_decimal_brackets_get_a_real_casimir_kept_by_taylor_lanes() -> None:
    """c with entries like 0.3 is an exact binary fraction whose smallest integer null vector
    has entries beyond 2^53 (this raised OverflowError inside numpy): the Casimir vector is the
    exact one rounded to float64 and scaled to max |k| = 1; Taylor-HJ (in lanes for any N) keeps
    Σ k_i ln x_i to round-off over 2,000 steps, and integer_null_space says why it refuses."""
    from poisson_rs.structures.log_canonical import integer_null_space

    system = pr.lotka_volterra(C5, [1.0, 2.0, 1.5, 0.5, 1.0])
    (k,) = system.structure.casimir_vectors
    assert k.dtype == np.float64 and np.max(np.abs(k)) == 1.0
    np.testing.assert_allclose(np.asarray(C5) @ k, 0.0, atol=1e-15)
    assert system.casimir_label.startswith("C = 0.721519 ln x₁ + 0.303797 ln x₂ + ln x₃")
    with pytest.raises(ValueError, match=r"integer null vector has an entry of .* beyond 2\^53"):
        integer_null_space(np.asarray(C5))
    rng = np.random.default_rng(11)
    x0 = np.exp(rng.uniform(-0.3, 0.3, (9, 5))) * np.array([1.0, 2.0, 1.5, 0.5, 1.0])
    traj = pr.integrate(pr.log_canonical_taylor(system, 3), x0, 0.05, 2000, every=100)
    drift = np.abs(system.casimirs(traj) - system.casimirs(x0)[:, None, :])
    assert drift.max() < 1e-12
    # RK4 in x does not keep it: the check can fail.
    rk4 = pr.integrate(pr.log_canonical_classical(system, "rk4"), x0, 0.05, 2000, every=100)
    assert np.abs(system.casimirs(rk4) - system.casimirs(x0)[:, None, :]).max() > 1e-9


def test_integer_null_space_of_one_column() -> None:
    """A 1 × 1 zero matrix has the null space (1): sympy's ilcm needs two arguments."""
    from poisson_rs.structures.log_canonical import integer_null_space

    assert integer_null_space(np.zeros((1, 1))).tolist() == [[1]]
    assert integer_null_space(np.zeros((2, 2))).tolist() == [[1, 0], [0, 1]]


def test_the_coordinate_change_is_libms_on_every_cpu() -> None:
    """x ↔ q = ln x at the rollout's ends is libm's log and exp (Python's math module calls the
    same functions), bit for bit, including overflow to inf, subnormal results and NaN; NumPy's
    are CPU-dispatched and differ in the last bit on some arguments (on AVX-512 machines)."""
    import math

    from poisson_rs import _core

    rng = np.random.default_rng(17)
    q = np.concatenate(
        [rng.uniform(-30.0, 30.0, 5009), [-745.0, -708.5, 709.9, 710.0, 1e4, -np.inf, np.nan]]
    ).reshape(-1, 3, 4)
    want = np.array([math.exp(v) if v < 709.8 else math.inf for v in q.ravel()])
    got = q.copy()
    _core.exp_in_place(got)
    np.testing.assert_array_equal(got.ravel().view(np.int64)[:-1], want.view(np.int64)[:-1])
    assert np.isnan(got.ravel()[-1])
    x = np.exp(rng.uniform(-30.0, 30.0, 4000)).reshape(100, 40)
    want_log = np.array([math.log(v) for v in x.ravel()])
    _core.log_in_place(x)
    np.testing.assert_array_equal(x.ravel().view(np.int64), want_log.view(np.int64))
    with pytest.raises(ValueError, match="q must be a C-contiguous float64 array"):
        _core.exp_in_place(np.zeros((4, 6))[:, ::2])
    with pytest.raises(TypeError):
        _core.log_in_place(np.zeros(3, dtype=np.float32))
    # The rollouts' own bits through it: tests/test_rollout_digests.py (lv-*).
