"""Recognition of the exact structure behind a polynomial bivector: Lie–Poisson (so(3) and
sl(2) as Nambu brackets), affine (PNN's extended pendulum), log-canonical (a 3-species
Lotka–Volterra); the exact system's vector field against the bivector's (which also fixes the
sign convention c_ijk = −a_ijk), a near miss refused with a note, and the Casimir kept to
round-off by the exact groupoid where the order-n realization drifts."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.structures.polynomial import (
    PolynomialBivector,
    PolynomialPoissonSystem,
    RealizationTaylorIntegrator,
)
from poisson_rs.structures.recognition import Recognition, recognize

EPS = np.zeros((3, 3, 3))
for _i, _j, _k in itertools.permutations(range(3)):
    EPS[_i, _j, _k] = np.linalg.det(np.eye(3)[[_i, _j, _k]])

#: Rock–paper–scissors Lotka–Volterra: ẋ_i = x_i Σ_j c_ij x_j with H = x1 + x2 + x3, whose
#: orbits close on the simplex; c (1, 1, 1) = 0, so ln x1 + ln x2 + ln x3 is a Casimir.
RPS_C = [[0.0, 1.0, -1.0], [-1.0, 0.0, 1.0], [1.0, -1.0, 0.0]]


def lotka_volterra_bivector(eps: float = 0.0) -> PolynomialBivector:
    """π_ij = c_ij x_i x_j (1 + eps x1): a conformal Nambu bracket f ε∇C with C = ln(x1x2x3),
    f = x1x2x3(1 + eps x1), so Poisson for every eps; log-canonical only at eps = 0."""
    f = f"(1 + {eps}*x1)"
    return PolynomialBivector(
        3, {(0, 1): f"x1*x2*{f}", (0, 2): f"-x1*x3*{f}", (1, 2): f"x2*x3*{f}"}
    )


def pendulum_bivector() -> PolynomialBivector:
    """PNN's extended pendulum: {u, v} = −1, {u, r} = −2v, {v, r} = 2u."""
    return PolynomialBivector(3, {(0, 1): "-1", (0, 2): "-2*x2", (1, 2): "2*x1"})


def e2_constants() -> np.ndarray:
    """e(2) with {u, r} = −2v, {v, r} = 2u in the package convention."""
    c = np.zeros((3, 3, 3))
    c[0, 2, 1], c[2, 0, 1] = 2.0, -2.0
    c[1, 2, 0], c[2, 1, 0] = -2.0, 2.0
    return c


BRACKETS = {
    "so3": lambda: PolynomialBivector.nambu("x1**2 + x2**2 + x3**2"),
    "sl2": lambda: PolynomialBivector.nambu("x1**2 + x2**2 - x3**2"),
    "pendulum": pendulum_bivector,
    "lotka_volterra": lotka_volterra_bivector,
}
KIND = {
    "so3": "lie_poisson",
    "sl2": "lie_poisson",
    "pendulum": "affine",
    "lotka_volterra": "log_canonical",
}


def test_so3_and_sl2_nambu_brackets_are_lie_poisson() -> None:
    """C = |x|²: π_ij = 2 ε_ijk x_k, so c = −2ε. C = x1² + x2² − x3²: π = (2x3·(−1), …) read
    off the same way; both algebras are accepted by LieAlgebra's Jacobi check."""
    found = recognize(BRACKETS["so3"]())
    assert (found.kind, found.residual, found.note) == ("lie_poisson", 0.0, "lie-poisson exactly")
    np.testing.assert_array_equal(found.data.c, -2.0 * EPS)
    sl2 = recognize(BRACKETS["sl2"]())
    assert sl2.kind == "lie_poisson" and sl2.residual == 0.0
    # π_12 = ∂_3 C = −2 x3, π_23 = ∂_1 C = 2 x1, π_13 = −∂_2 C = −2 x2.
    expected = -2.0 * EPS
    expected[:, :, 2] *= -1.0
    np.testing.assert_array_equal(sl2.data.c, expected)


def test_extended_pendulum_is_affine_with_its_cocycle() -> None:
    found = recognize(pendulum_bivector())
    assert (found.kind, found.residual) == ("affine", 0.0)
    algebra, omega = found.data
    np.testing.assert_array_equal(algebra.c, e2_constants())
    np.testing.assert_array_equal(omega, [[0, -1, 0], [1, 0, 0], [0, 0, 0]])
    h = "x1**2/2 + x2**2/2 - x2**4/24"
    exact = PolynomialPoissonSystem(pendulum_bivector(), h).exact_system()
    w = [[0, -1, 0], [1, 0, 0], [0, 0, 0]]
    ref = pr.affine_poisson_system(
        e2_constants(), w, {(2, 0, 0): 0.5, (0, 2, 0): 0.5, (0, 4, 0): -1.0 / 24.0}
    )
    assert isinstance(exact, pr.AffinePoissonSystem) and exact == ref


def test_lotka_volterra_bivector_is_log_canonical() -> None:
    found = recognize(lotka_volterra_bivector())
    assert (found.kind, found.residual) == ("log_canonical", 0.0)
    assert found.data == pr.LogCanonical(RPS_C)
    exact = PolynomialPoissonSystem(lotka_volterra_bivector(), "x1 + x2 + x3").exact_system()
    assert isinstance(exact, pr.LogCanonicalSystem)
    assert exact.log_hamiltonian == pr.LogPolynomial(
        {(1, 0, 0): 1.0, (0, 1, 0): 1.0, (0, 0, 1): 1.0}, [0.0, 0.0, 0.0]
    )
    np.testing.assert_array_equal(exact.structure.casimir_vectors, [[1, 1, 1]])


def _random_hamiltonian(rng: np.random.Generator, degree: int) -> str:
    """A dense random polynomial in x1, x2, x3 of the given degree (constant term included)."""
    terms = []
    for e in itertools.product(range(degree + 1), repeat=3):
        if sum(e) <= degree:
            terms.append(f"({rng.normal():.17g})*x1**{e[0]}*x2**{e[1]}*x3**{e[2]}")
    return " + ".join(terms)


@pytest.mark.parametrize("name", list(BRACKETS))
def test_exact_system_has_the_bivector_vector_field(name: str) -> None:
    """ẋ = π∇H of the bivector system against the exact system's own vector field (its own
    code: LiePoissonSystem's μ̇_j = Σ c[i,j,k] ∂_iH μ_k, the affine extension, q̇ = c∇_qH) for a
    seeded random cubic H, at seeded random states: ≤ 1e-12 relative. This fixes the sign
    c_ijk = −a_ijk: the opposite sign would flip the linear part of the field."""
    rng = np.random.default_rng(26)
    system = PolynomialPoissonSystem(BRACKETS[name](), _random_hamiltonian(rng, 3))
    exact = system.exact_system()
    assert exact is not None and exact.kind == KIND[name]
    low = 0.1 if name == "lotka_volterra" else -1.5
    x = rng.uniform(low, 1.5, size=(32, 3))
    want = system.vector_field(x)
    got = np.asarray(exact.vector_field(x))
    assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()
    assert f"exact realization: {KIND[name].replace('_', '-')}" in repr(system)


def test_a_near_miss_keeps_the_order_n_realization_with_a_note() -> None:
    """A bracket 1e-3 off log-canonical (still Poisson) is not recognised at the default tol:
    no exact system, and the note says which form was closest and how far. A tol above its
    residual accepts it, saying the residual."""
    near = lotka_volterra_bivector(1e-3)
    found = recognize(near)
    assert found.kind is None and found.data is None
    assert 1e-3 <= found.residual <= 1e-2
    assert found.note.startswith("not recognised: closest exact form log-canonical, ")
    assert f"{found.residual:.1e} off" in found.note
    system = PolynomialPoissonSystem(near, "x1 + x2 + x3")
    assert system.exact_system() is None
    assert repr(system).endswith("exact realization: none)")
    loose = recognize(near, tol=1e-2)
    assert loose.kind == "log_canonical"
    assert loose.note == f"log-canonical to a relative residual {loose.residual:.1e}"


def test_a_genuinely_nonlinear_bracket_is_not_recognised() -> None:
    found = recognize(PolynomialBivector.nambu("x1**2/2 + x2**2/2 + x3**2/2 + x1**3/3"))
    assert found.kind is None and found.residual > 0.1
    assert isinstance(found, Recognition)


def test_bad_arguments() -> None:
    with pytest.raises(TypeError, match="bivector must be a PolynomialBivector"):
        recognize("x1*x2")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"tol must be a number in \[0, 1\)"):
        recognize(pendulum_bivector(), tol=-1.0)


def test_lotka_volterra_bivector_keeps_its_casimir_through_the_exact_system() -> None:
    """Lotka–Volterra written as a PolynomialBivector, Taylor-HJ m = 3 at h = 0.1 over 10⁴
    steps: through the exact system (the log-canonical groupoid) the Casimir ln x1x2x3 stays
    within 1e-13 (measured 8.3e-15); the order-3 realization drifts by 2.6e-6 (measured)."""
    system = PolynomialPoissonSystem(lotka_volterra_bivector(), "x1 + x2 + x3")
    exact = system.exact_system()
    x0 = np.array([[1.0, 0.8, 1.2], [0.5, 1.0, 1.5], [0.3, 0.6, 2.1]])
    traj = pr.integrate(pr.log_canonical_taylor(exact, 3), x0, 0.1, 10_000)
    c = exact.casimirs(traj)
    exact_drift = float(np.abs(c - c[:, :1]).max())
    approx = pr.integrate(RealizationTaylorIntegrator(system, 3), x0, 0.1, 10_000)
    c = exact.casimirs(approx)
    approx_drift = float(np.abs(c - c[:, :1]).max())
    assert exact_drift <= 1e-13
    assert approx_drift > 1e-7
    # Both integrate the same flow: the order-4 schemes agree to their error, not to round-off.
    assert np.abs(traj - approx).max() < 0.05


def test_the_single_name_steps_a_recognised_bivector_on_its_exact_groupoid() -> None:
    """Lotka–Volterra written as a polynomial bivector: pr.taylor_integrator picks the exact
    log-canonical groupoid by itself and keeps ln x1x2x3 to round-off over 10⁴ steps, where
    the order-n realization (still there by name) drifts; a near miss keeps the realization."""
    import poisson_rs as pr
    from poisson_rs.structures.polynomial import PolynomialBivector, PolynomialPoissonSystem

    entries = {(0, 1): "x1*x2", (1, 2): "x2*x3", (0, 2): "-x1*x3"}
    system = PolynomialPoissonSystem(PolynomialBivector(3, entries), "x1 + x2 + x3")
    assert system.taylor_charts()[0] == "log"
    x0 = np.array([[1.0, 0.8, 1.2], [0.5, 1.5, 1.0]])
    traj = pr.integrate(pr.taylor_integrator(system, 3), x0, 0.1, 10_000, every=100)
    drift = np.abs(np.log(traj).sum(-1) - np.log(x0).sum(-1)[:, None]).max()
    assert drift <= 1e-13
    traj = pr.integrate(pr.taylor_integrator(system, 3, "realization"), x0, 0.1, 1000, every=100)
    assert np.abs(np.log(traj).sum(-1) - np.log(x0).sum(-1)[:, None]).max() > 1e3 * drift
    # π·(1 + x1/1000) is still Poisson in 3-D (a conformal factor keeps v·curl v = 0).
    near = {k: f"({v})*(1 + x1/1000)" for k, v in entries.items()}
    off = PolynomialPoissonSystem(PolynomialBivector(3, near), "x1 + x2 + x3")
    assert off.taylor_charts()[0] == "realization"
