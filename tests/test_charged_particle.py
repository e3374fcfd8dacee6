"""The charged particle with B, H and the vector potential as expressions: PNN's Lorentz-force
system (B = |x|, A = |x|/3 (−x₂, x₁), H = |v|²/2 + 1/(100|x|)) on the package's structure."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.structures.charged_particle import ChargedParticle, charged_particle

SCENE = Path(__file__).resolve().parents[1] / "scenes" / "charged_particle_pnn.toml"
B = "sqrt(x1**2 + x2**2)"
A = ["-sqrt(x1**2 + x2**2)*x2/3", "sqrt(x1**2 + x2**2)*x1/3"]
H = "(x3**2 + x4**2)/2 + 1/(100*sqrt(x1**2 + x2**2))"
#: PNN's state z0 = (v, x) = (1, 0.5, 0.5, 1), in the package's order (x, v).
X0 = np.array([[0.5, 1.0, 1.0, 0.5]])


@pytest.fixture(scope="module")
def particle() -> ChargedParticle:
    return ChargedParticle(B, H, potential=A)


def energy(z: np.ndarray) -> np.ndarray:
    """H written out here (the oracle of the system's own expression)."""
    return 0.5 * (z[..., 2] ** 2 + z[..., 3] ** 2) + 0.01 / np.hypot(z[..., 0], z[..., 1])


def test_the_field_is_the_lorentz_force(particle: ChargedParticle) -> None:
    """ẋ = v, v̇ = B(x) (v₂, −v₁) − ∇φ with φ = 1/(100|x|), written out by hand."""
    z = np.random.default_rng(3).normal(size=(5, 4))
    x, v = z[:, :2], z[:, 2:]
    r = np.hypot(x[:, 0], x[:, 1])
    vdot = r[:, None] * np.stack([v[:, 1], -v[:, 0]], axis=1) + 0.01 * x / r[:, None] ** 3
    np.testing.assert_allclose(particle.vector_field(z), np.hstack([v, vdot]), rtol=1e-13)
    np.testing.assert_allclose(particle.hamiltonian(z), energy(z), rtol=1e-14)
    # p = v + A(x) and back.
    np.testing.assert_allclose(particle.from_canonical(particle.to_canonical(z)), z, rtol=1e-14)


def test_a_potential_whose_curl_is_not_b_is_refused() -> None:
    # curl (−x₂/2, x₁/2) = 1, not |x|.
    with pytest.raises(ValueError, match=r"^potential: curl A ≠ B"):
        ChargedParticle(B, H, potential=["-x2/2", "x1/2"])
    # The polynomial route checks a given potential too (exactly, by sympy).
    with pytest.raises(ValueError, match=r"^potential: curl A ≠ B"):
        ChargedParticle("1 + x1**2/4", potential=["0", "x1"])
    # Another gauge of the same B is accepted: A + ∇(x₁x₂).
    other = ChargedParticle(B, H, potential=[f"{A[0]} + x2", f"{A[1]} + x1"])
    assert other.potential[0].endswith("+ x2")
    with pytest.raises(ValueError, match="potential must be 2 expressions"):
        ChargedParticle(B, H, potential=[A[0]])


def test_a_field_that_is_not_a_polynomial_needs_its_potential() -> None:
    with pytest.raises(ValueError, match=r"^potential: B = sqrt.*is not a polynomial"):
        ChargedParticle(B, H)
    with pytest.raises(ValueError, match=r"field\[0\]: unknown name 'y'"):
        ChargedParticle("sqrt(y)", H, potential=A)


def test_a_state_at_x_0_is_refused_naming_it(particle: ChargedParticle) -> None:
    bad = [[0.0, 0.0, 1.0, 0.5]]
    for stepper in (pr.taylor_integrator(particle, 3), pr.classical(particle, "rk4")):
        with pytest.raises(
            ValueError, match=r"^x0 must be finite, with H.*state 0 is \[0\.0, 0\.0"
        ):
            pr.integrate(stepper, bad, 0.1, 5)
    with pytest.raises(ValueError, match=r"^x0 must be"):
        pr.reference_solution(particle, bad, [0.0, 1.0])
    assert particle.in_domain(np.array([[0.0, 0.0, 1.0, 0.5], *X0])).tolist() == [False, True]


def test_jets_orders_1_3_5_fit_orders_2_4_6_against_dop853(particle: ChargedParticle) -> None:
    """|x| stays in [0.5, 1.6] on this orbit: far from the singularity at x = 0."""
    ref = particle.reference_solution(X0, np.linspace(0.0, 1.0, 11))
    r = np.hypot(ref[0, :, 0], ref[0, :, 1])
    assert r.min() > 0.5
    for m in (1, 3, 5):
        stepper = pr.taylor_integrator(particle, m)
        assert stepper.name == f"taylor{m}-canonical"
        errs = [np.abs(pr.integrate(stepper, X0, 1.0 / n, n)[:, -1] - ref[:, -1]).max()
                for n in (8, 16)]  # fmt: skip
        assert abs(np.log2(errs[0] / errs[1]) - (m + 1)) < 0.3, (m, errs)
    rk4 = pr.classical(particle, "rk4")
    errs = [np.abs(pr.integrate(rk4, X0, 1.0 / n, n)[:, -1] - ref[:, -1]).max() for n in (8, 16)]
    assert abs(np.log2(errs[0] / errs[1]) - 4) < 0.3, errs


def test_energy_is_kept_to_the_orders_level(particle: ChargedParticle) -> None:
    """Over 400 steps of h = 0.1 the energy error of Taylor-HJ m = 3 is O(h⁴) and bounded
    (symplectic in (x, p)), m = 1's O(h²); the midpoint rule on (x, v) is not symplectic there."""
    e0 = energy(X0)[0]
    drift = {}
    for m in (1, 3):
        traj = pr.integrate(pr.taylor_integrator(particle, m), X0, 0.1, 400)[0]
        de = np.abs(energy(traj) - e0) / e0
        drift[m] = de.max()
        assert de[-100:].max() < 2.0 * de[:200].max() + 1e-14, m  # bounded, no drift
    assert drift[3] < 1e-5 < drift[1] < 1e-2, drift
    traj = pr.integrate(pr.classical(particle, "midpoint"), X0, 0.1, 40)[0]
    assert np.abs(energy(traj) - e0).max() / e0 < 1e-2


def test_round_trips(particle: ChargedParticle) -> None:
    again = pr.system_from_dict(particle.to_dict())
    assert again == particle and again.to_dict()["potential"] == A
    stepper = pr.taylor_integrator(particle, 3)
    for s in (stepper, pr.classical(particle, "rk4")):
        np.testing.assert_array_equal(
            pr.integrate(pickle.loads(pickle.dumps(s)), X0, 0.1, 5), pr.integrate(s, X0, 0.1, 5)
        )


def test_a_polynomial_field_with_an_expression_hamiltonian() -> None:
    """B polynomial, H not: the potential is derived, Taylor-HJ by jets, order 4 for m = 3."""
    particle = ChargedParticle("1 + x1**2/4", "(x3**2 + x4**2)/2 + cos(x1)")
    assert particle.potential == ("0", "x1**3/12 + x1")
    x0 = np.array([[0.3, -0.2, 1.0, 0.5]])
    ref = particle.reference_solution(x0, [1.0])[:, -1]
    stepper = pr.taylor_integrator(particle, 3)
    errs = [np.abs(pr.integrate(stepper, x0, 1.0 / n, n)[:, -1] - ref).max() for n in (8, 16)]
    assert abs(np.log2(errs[0] / errs[1]) - 4) < 0.3, errs


def test_the_pnn_scene_runs_through_demo_and_select(tmp_path: Path) -> None:
    from poisson_rs.cli import main
    from poisson_rs.scenes import load_scene

    scene = load_scene(SCENE)
    assert scene.system == ChargedParticle(B, H, potential=A, name="PNN charged particle")
    argv = ["demo", "--scene", str(SCENE), "--steps", "20", "--out", str(tmp_path / "d")]
    assert main(argv) == 0
    metrics = (tmp_path / "d" / "metrics.csv").read_text()
    assert "taylor3-canonical" in metrics and "rk4" in metrics
    out = tmp_path / "select.json"
    assert main(["select", str(SCENE), "--T", "1", "--budget", "1", "--json", str(out)]) == 0
    assert "taylor3-canonical" in out.read_text()


def test_learning_offers_the_degrees_whose_polynomial_fits_the_tape(
    particle: ChargedParticle, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Degree 4 in (x, p − A(x)), 291 instructions with 15 values live, fits the core's tape; a
    degree that does not is not offered, not failed (here under a tape of 12 live values)."""
    import poisson_rs.expressions as ex

    assert particle.learn_degrees() == (2, 3, 4)
    monkeypatch.setattr(ex, "MAX_LIVE", 12)
    assert particle.learn_degrees() == (2, 3)
    family = particle.hamiltonian_family(2)
    assert family.order == 3 and len(family) == 14


@pytest.mark.parametrize("field", ["2**2**2**2**2**2", "(x1**64)**64", "x1**" + "9" * 40])
def test_hostile_field_texts_are_refused_before_sympy(monkeypatch, field: str) -> None:
    """Texts outside the expression grammar's bounds are refused by it, naming the field: sympy
    (unbounded on such texts) never sees them."""
    import sympy

    def never(*args: object, **kwargs: object) -> None:
        raise AssertionError("sympy saw the text")

    monkeypatch.setattr(sympy, "sympify", never)
    with pytest.raises(ValueError, match="field"):
        charged_particle(field)


def test_expression_hamiltonians_keep_the_field_and_potential(particle: ChargedParticle) -> None:
    """``expression_system`` (and so ``pr.with_hamiltonian``) is the same B and A with a new H: a
    charged particle again, whose
    field is the Lorentz force of that H (written out by hand), and the term libraries of
    ``pr.learn`` apply (their H written in the component names x₁ … v₂)."""
    from poisson_rs.hamiltonian_library import library_families, supports_library

    other = particle.expression_system("(v₁**2 + v₂**2)/2 + x₁**2 * cos(x₂)", name="other")
    assert isinstance(other, ChargedParticle)
    assert (
        pr.with_hamiltonian(particle, "(v₁**2 + v₂**2)/2 + x₁**2 * cos(x₂)", name="other") == other
    )
    assert (other.field, other.potential, other.name) == (particle.field, particle.potential,
                                                          "other")  # fmt: skip
    z = np.random.default_rng(4).normal(size=(5, 4))
    x, v = z[:, :2], z[:, 2:]
    r = np.hypot(x[:, 0], x[:, 1])
    grad_phi = np.stack([2 * x[:, 0] * np.cos(x[:, 1]), -(x[:, 0] ** 2) * np.sin(x[:, 1])], axis=1)
    vdot = r[:, None] * np.stack([v[:, 1], -v[:, 0]], axis=1) - grad_phi
    np.testing.assert_allclose(other.vector_field(z), np.hstack([v, vdot]), rtol=1e-13)
    assert supports_library(particle)
    names = [f.name for f in library_families(particle, None, 4)]
    assert names == [
        "poly2+trig",
        "poly3+trig",
        "poly2+logdist",
        "poly2+dist^-1",
        "poly2+exp",
        "poly2+trig+trigdiff",
        "poly2+trig+xtrig",
        "poly2+trig+harmonics",
    ]
    dist = library_families(particle, None, 4)[3]
    theta = np.zeros(len(dist))
    theta[dist.exponents.index((0, 0, 2, 0))] = theta[dist.exponents.index((0, 0, 0, 2))] = 0.5
    theta[dist.exponents.index(("radius", -1, 0))] = 0.01
    np.testing.assert_allclose(dist.system(theta).hamiltonian(z), energy(z), rtol=1e-14)


def test_the_library_recovers_pnns_hamiltonian(particle: ChargedParticle) -> None:
    """PNN's state, 61 exact records at h = 0.1: poly2+dist^-1 fitted through Taylor-HJ by jets
    (m = 5) keeps exactly |v|²/2 + 1/(100|x|), every coefficient within 1e-6 of the true one, and
    the learned system steps as the true one does (T = 30 and 10×:
    benches/charged_particle_pnn.py runs pr.learn's whole search). Through m = 3 the integrator's
    own error (~1e-4 over the records) would leak into the coefficients."""
    from poisson_rs.hamiltonian_library import LibraryFamily
    from poisson_rs.learn.data import prepare
    from poisson_rs.learn.structure_fit import fit_structure_hamiltonian

    h = 0.1
    records = np.asarray(particle.reference_solution(X0, h * np.arange(61)))
    data = prepare(list(records), h, None, seed=0, system=particle)
    family = LibraryFamily(particle, 2, 5, trig=False, distance_powers=(-1,))
    fit = fit_structure_hamiltonian(data, particle, 2, order=5, family=family)
    truth = dict.fromkeys(family.exponents, 0.0)
    truth.update({(0, 0, 2, 0): 0.5, (0, 0, 0, 2): 0.5, ("radius", -1, 0): 0.01})
    learned = dict(zip(fit.family.exponents, fit.theta, strict=True))
    assert set(learned) == {(0, 0, 2, 0), (0, 0, 0, 2), ("radius", -1, 0)}
    assert max(abs(learned.get(k, 0.0) - t) for k, t in truth.items()) <= 1e-6, learned
    true = pr.taylor_integrator(particle, 5)
    a = pr.integrate(true, records[0, -1], h, 40)
    b = pr.integrate(fit.stepper, records[0, -1], h, 40)
    assert np.abs(a - b).max() <= 1e-6
