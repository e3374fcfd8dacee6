"""The term library beyond polynomials (:mod:`poisson_rs.hamiltonian_library`) and
``pr.learn`` reaching for it where no polynomial explains the data."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.hamiltonian_library import (
    DISTANCE_POWERS,
    LibraryFamily,
    distance_pairs,
    library_families,
    linear_forms,
    supports_library,
)
from poisson_rs.learn.data import prepare
from poisson_rs.learn.structure_fit import fit_structure_hamiltonian
from poisson_rs.protocols import NEWTON_MAX_ITER, NEWTON_TOL
from poisson_rs.scenes import load_scene


@pytest.fixture(scope="module")
def pendulum():
    """PNN's extended pendulum: the affine bracket with H = ½u² − cos v + u(r − u² − v²)."""
    return load_scene("scenes/extended_pendulum_pnn.toml").system


def test_gradients_match_finite_differences(pendulum):
    fam = LibraryFamily(pendulum.base, 2)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(6, 3))
    g = fam.gradients(x)
    eps = 1e-6
    for i in range(3):
        step = np.zeros(3)
        step[i] = eps
        plus = [fam.system(np.eye(len(fam))[m]).hamiltonian(x + step) for m in range(len(fam))]
        minus = [fam.system(np.eye(len(fam))[m]).hamiltonian(x - step) for m in range(len(fam))]
        fd = (np.stack(plus, axis=1) - np.stack(minus, axis=1)) / (2 * eps)
        np.testing.assert_allclose(g[:, i, :], fd, atol=1e-8)


def test_text_is_the_sum_of_the_terms(pendulum):
    fam = LibraryFamily(pendulum.base, 3)
    rng = np.random.default_rng(1)
    theta = rng.normal(size=len(fam))
    x = rng.normal(size=(5, 3))
    system = fam.system(theta)
    each = np.stack(
        [fam.system(np.eye(len(fam))[m]).hamiltonian(x) for m in range(len(fam))], axis=1
    )
    np.testing.assert_allclose(system.hamiltonian(x), each @ theta, rtol=1e-13, atol=1e-13)
    assert fam.name == "poly3+trig" and len(fam) == 19 + 6


def test_restrict_and_bad_keys(pendulum):
    fam = LibraryFamily(pendulum.base, 2)
    sub = fam.restrict([(2, 0, 0), ("cos", 1)])
    assert sub.exponents == [(2, 0, 0), ("cos", 1)]
    assert sub.text([0.5, -1.0]) == "(0.5)*u**2 + (-1.0)*cos(v)"
    with pytest.raises(ValueError, match="keys must be terms of the library poly2"):
        fam.restrict([("tan", 0)])


def test_only_structures_with_a_jet_realization_offer_it(pendulum):
    assert supports_library(pendulum.base)
    assert not supports_library(pr.lotka_volterra([[0, 1], [-1, 0]], [1, 2]))


def test_the_gauge_is_the_structures_own(pendulum):
    """A library's H is identifiable up to what the structure's own family says: a Casimir on
    the affine bracket, nothing on the charged particle's symplectic one."""
    from poisson_rs.structures.charged_particle import charged_particle

    (lib, *_) = library_families(pendulum.base, None, 3)
    assert lib.gauge == pendulum.base.hamiltonian_family(2, None).gauge
    assert "Casimir of the central extension" in lib.gauge
    cp = charged_particle("1 + x1**2/4", "x3**2/2 + x4**2/2")
    (lib, *_) = library_families(cp, None, 3)
    assert "symplectic" in lib.gauge and "a Casimir of" not in lib.gauge


def test_restrict_hands_the_gauge_on_without_asking_the_structure_again(pendulum, monkeypatch):
    """The structure's polynomial family is built once per library, not once per refit."""
    base = pendulum.base
    asked = []
    offer = base.hamiltonian_family
    monkeypatch.setattr(base, "hamiltonian_family", lambda *a: asked.append(a) or offer(*a))
    fam = LibraryFamily(base, 2)
    sub = fam.restrict([(2, 0, 0), ("cos", 1)])
    assert len(asked) == 1 and sub.gauge == fam.gauge == offer(2, None).gauge


def test_learn_finds_the_pendulums_cosine_and_beats_every_polynomial(pendulum):
    """PNN's protocol (3 states, h = 0.1, 100 steps): no polynomial degree reaches the noise
    level; the library's poly3+trig does, and its field is the true one up to the Casimir."""
    h = 0.1
    states = np.array([[0.0, 1.0, 1.0], [0.0, 1.5, 2.35], [0.0, 2.0, 4.2]])
    trajs = list(np.asarray(pr.reference_solution(pendulum, states, np.arange(101) * h)))
    stepper, report = pr.learn(trajs, h, structure=pendulum.base, seed=0, progress=False)
    families = [c.family for c in report.candidates]
    assert families[:3] == ["poly2", "poly3", "poly4"]
    assert report.kept.family == "poly3+trig"
    assert report.kept.one_step <= report.threshold
    assert all(c.one_step > 100 * report.kept.one_step for c in report.candidates[:3])
    assert "cos(v)" in report.hamiltonian_text
    x = np.random.default_rng(2).uniform(-1.0, 1.0, size=(20, 3))
    np.testing.assert_allclose(
        report.system.vector_field(x), pendulum.vector_field(x), rtol=0, atol=1e-5
    )
    # The Casimir r − u² − v² is kept to round-off by the learned jets stepper.
    roll = pr.integrate(stepper, states[0], h, 200)
    c = roll[:, 2] - roll[:, 0] ** 2 - roll[:, 1] ** 2
    assert np.max(np.abs(c - c[0])) < 1e-12


# Log-distance terms ln|z_a − z_b|² of the planar points (x1, x2), (x3, x4), (x5, x6).

GAMMA = (1.0, 1.0, 0.5)


@pytest.fixture(scope="module")
def vortices():
    """The three point vortices' scene: the expression system (true H) on its bracket."""
    return load_scene("scenes/point_vortices.toml")


H = 0.05


def _vortex_records(scene, n_records: int) -> list[np.ndarray]:
    """Exact records from the scene's two states, h = 0.05."""
    starts = scene.states()
    return list(np.asarray(pr.reference_solution(scene.system, starts, np.arange(n_records) * H)))


def test_log_distance_terms_value_and_gradient_match_autograd(vortices):
    torch = pytest.importorskip("torch")
    fam = LibraryFamily(vortices.system.base, 1, trig=False, log_distances=True)
    logs = [m for m, k in enumerate(fam.exponents) if k[0] == "logdist"]
    assert [fam.exponents[m] for m in logs] == [
        ("logdist", 0, 1),
        ("logdist", 0, 2),
        ("logdist", 1, 2),
    ]
    x = np.random.default_rng(3).normal(size=(7, 6))
    xt = torch.tensor(x, requires_grad=True)
    for m in logs:
        _, a, b = fam.exponents[m]
        d = xt[:, 2 * a : 2 * a + 2] - xt[:, 2 * b : 2 * b + 2]
        phi = torch.log((d * d).sum(dim=1))
        (grad,) = torch.autograd.grad(phi.sum(), xt)
        np.testing.assert_allclose(fam.gradients(x)[:, :, m], grad.numpy(), rtol=1e-13, atol=1e-13)
        # The text the learned system steps is the same function.
        value = fam.system(np.eye(len(fam))[m]).hamiltonian(x)
        np.testing.assert_allclose(value, phi.detach().numpy(), rtol=1e-13, atol=1e-13)


def test_log_distances_need_an_even_dimension_of_at_least_4(pendulum, vortices):
    """The pairing (x1, x2), (x3, x4), … is refused on odd dimensions, and pr.learn's libraries
    leave the log-distance terms out there."""
    with pytest.raises(ValueError, match="dimension must be even and at least 4, got 3"):
        LibraryFamily(pendulum.base, 2, log_distances=True)
    with pytest.raises(ValueError, match="got 2"):
        distance_pairs(2)
    assert [f.name for f in library_families(pendulum.base, None, 12)] == [
        "poly2+trig",
        "poly3+trig",
        "poly2+exp",
        "poly2+trig+trigdiff",
        "poly2+trig+xtrig",
        "poly2+trig+harmonics",
    ]
    # In 6-D every library of degree ≤ 3 fits the expression limits (95 terms for poly3+trig,
    # 69 for the linear forms'); of the 8-D ones, poly3+trig (180 terms) does too.
    assert [f.name for f in library_families(vortices.system.base, None, 12)] == [
        "poly2+trig",
        "poly3+trig",
        "poly2+logdist",
        "poly2+dist^-1",
        "poly2+exp",
        "poly2+trig+trigdiff",
        "poly2+trig+xtrig",
        "poly2+trig+harmonics",
    ]
    four = load_scene("scenes/point_vortices_4.toml").system.base
    assert "poly3+trig" in [f.name for f in library_families(four, None, 12)]
    # Beyond them, a family is still left out (poly4+trig in 8-D: over 1024 instructions).
    assert not LibraryFamily(four, 4).writable()
    assert distance_pairs(8) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]


def test_fit_recovers_the_vortex_hamiltonian(vortices):
    """Exact records (2 × 41, h = 0.05): the poly2+logdist fit keeps exactly the three
    log-distances, with −Γ_aΓ_b/(4π) to 1e-6 relative (H up to a constant: the library has none),
    and its stepper's error at T = 5 is within 2× of the true H through the same integrator
    (T = 100: benches/library_vortices.py)."""
    base = vortices.system.base
    trajs = _vortex_records(vortices, 41)
    data = prepare(trajs, H, None, seed=0, system=base)
    fam = LibraryFamily(base, 2, trig=False, log_distances=True)
    fit = fit_structure_hamiltonian(data, base, 2, family=fam)
    assert fit.family.exponents == [("logdist", 0, 1), ("logdist", 0, 2), ("logdist", 1, 2)]
    truth = np.array([-GAMMA[a] * GAMMA[b] / (4 * np.pi) for a, b in distance_pairs(6)])
    assert np.max(np.abs(fit.theta - truth)) <= 1e-6 * np.max(np.abs(truth))
    x0 = np.array([0.7, 0.4, -0.7, 0.3, 0.2, -1.0])
    ref = np.asarray(pr.reference_solution(vortices.system, x0[None], [0.0, 5.0]))[0, -1]
    true = vortices.system.taylor_integrator(fam.order, tol=NEWTON_TOL, max_iter=NEWTON_MAX_ITER)
    err_true = np.max(np.abs(pr.integrate(true, x0, H, 100)[-1] - ref))
    err_learned = np.max(np.abs(pr.integrate(fit.stepper, x0, H, 100)[-1] - ref))
    assert err_learned <= 2.0 * err_true


def test_coinciding_points_are_refused_with_one_clear_error(vortices):
    """A record with z_1 = z_2 (a rotation of point 1 about the origin under the bracket's own
    H = x1² + x2², starting on point 2) cannot be fitted by ln|z_1 − z_2|²."""
    base = vortices.system.base
    start = np.array([[0.5, -0.25, 0.5, -0.25, 1.0, 1.0]])
    bad = list(np.asarray(pr.reference_solution(base, start, np.arange(6) * H)))
    trajs = _vortex_records(vortices, 6) + bad
    data = prepare(trajs, H, None, seed=0, system=base)
    fam = LibraryFamily(base, 2, trig=False, log_distances=True)
    message = r"trajectories: 1 record\(s\) put points 1 and 2 at the same place"
    with pytest.raises(ValueError, match=message):
        fit_structure_hamiltonian(data, base, 2, family=fam)
    # pr.learn's search passes over the library singular on these records and reports on the
    # families that apply, rather than stopping on the first that cannot.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, report = pr.learn(trajs, H, structure=base, max_degree=2, seed=0, progress=False)
    tried = [c.family for c in report.candidates]
    assert "poly2+logdist" not in tried and "poly2+trig" in tried
    assert report.kept.family in tried


# Powers of distances |z_a − z_b|^p and |z_a|^p, and planar Kepler in (q1, q2, p1, p2).


@pytest.fixture(scope="module")
def canonical():
    """The constant bracket {q_i, p_i} = 1 on (q1, q2, p1, p2) = (x1 … x4): the planar points
    of the library are z_0 = q and z_1 = p."""
    structure = pr.PolynomialBivector(4, {(0, 2): "1", (1, 3): "1"})
    return pr.PolynomialPoissonSystem(structure, "x1**2 + x2**2", name="canonical")


def _periapsis(e: float, angle: float) -> np.ndarray:
    """(q, p) at periapsis of the Kepler orbit (GM = 1, a = 1) of eccentricity ``e``."""
    r, v = 1.0 - e, np.sqrt((1.0 + e) / (1.0 - e))
    c, s = np.cos(angle), np.sin(angle)
    return np.array([r * c, r * s, -v * s, v * c])


def test_distance_power_terms_value_and_gradient_match_autograd(vortices):
    torch = pytest.importorskip("torch")
    fam = LibraryFamily(vortices.system.base, 1, trig=False, distance_powers=DISTANCE_POWERS)
    assert fam.name == "poly1+dist^-1+dist^-2+dist^-3" and len(fam) == 6 + 3 * 6
    powers = [m for m, k in enumerate(fam.exponents) if k[0] in ("dist", "radius")]
    assert [fam.exponents[m] for m in powers[:6]] == [
        ("dist", -1, 0, 1),
        ("dist", -1, 0, 2),
        ("dist", -1, 1, 2),
        ("radius", -1, 0),
        ("radius", -1, 1),
        ("radius", -1, 2),
    ]
    x = np.random.default_rng(4).normal(size=(7, 6))
    xt = torch.tensor(x, requires_grad=True)
    grads = fam.gradients(x)
    for m in powers:
        kind, p, a = fam.exponents[m][:3]
        d = xt[:, 2 * a : 2 * a + 2]
        if kind == "dist":
            b = fam.exponents[m][3]
            d = d - xt[:, 2 * b : 2 * b + 2]
        phi = torch.sqrt((d * d).sum(dim=1)) ** p
        (grad,) = torch.autograd.grad(phi.sum(), xt)
        np.testing.assert_allclose(grads[:, :, m], grad.numpy(), rtol=1e-12, atol=1e-13)
        # The text the learned system steps is the same function.
        value = fam.system(np.eye(len(fam))[m]).hamiltonian(x)
        np.testing.assert_allclose(value, phi.detach().numpy(), rtol=1e-13, atol=1e-13)


def test_distance_power_gradients_match_finite_differences(canonical):
    fam = LibraryFamily(canonical, 1, trig=False, distance_powers=(-1,))
    x = np.random.default_rng(5).normal(size=(6, 4))
    g = fam.gradients(x)
    eps = 1e-6
    for i in range(4):
        step = np.zeros(4)
        step[i] = eps
        fd = np.stack(
            [
                (fam.system(e).hamiltonian(x + step) - fam.system(e).hamiltonian(x - step))
                / (2 * eps)
                for e in np.eye(len(fam))
            ],
            axis=1,
        )
        np.testing.assert_allclose(g[:, i, :], fd, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("powers", [(0,), (2,), (-4,), (-1, -1), (1.0,), (True,), "-1", -1])
def test_bad_distance_powers_are_refused_naming_the_field(canonical, powers):
    with pytest.raises(ValueError, match=r"distance_powers must be distinct integers among"):
        LibraryFamily(canonical, 2, distance_powers=powers)


def test_distance_powers_need_planar_points_and_come_last(pendulum, canonical):
    with pytest.raises(ValueError, match="dimension must be even and at least 4, got 3"):
        LibraryFamily(pendulum.base, 2, distance_powers=(-1,))
    # After the cheaper libraries: 14 monomials + 1 log-distance, then + 3 inverse distances.
    # The linear forms' libraries (2n + n(n − 1) exponentials; n(n − 1) sines and cosines of
    # differences) after them, then the 2n² products x_j sin x_i, x_j cos x_i.
    families = library_families(canonical, None, 12)
    assert [f.name for f in families] == [
        "poly2+trig",
        "poly3+trig",
        "poly2+logdist",
        "poly2+dist^-1",
        "poly2+exp",
        "poly2+trig+trigdiff",
        "poly2+trig+xtrig",
        "poly2+trig+harmonics",
    ]
    assert [len(f) for f in families[2:]] == [
        15,
        17,
        14 + 20,
        14 + 8 + 12,
        14 + 8 + 32,
        14 + 8 + 16,
    ]
    dist = families[3]
    assert dist.description.endswith(
        "|z_a − z_b|^-1 and |z_a|^-1 of the points (x1, x2), (x3, x4) (17 terms)"
    )
    assert dist.text(np.r_[np.zeros(14), 0.0, -1.0, 0.0]) == "(-1.0)*(x1**2 + x2**2)**(-0.5)"
    assert families[-3].description.endswith(
        "sin and cos of each coordinate and sin and cos of x_i − x_j (34 terms)"
    )
    assert families[-2].description.endswith(
        "sin and cos of each coordinate and x_j sin x_i and x_j cos x_i (54 terms)"
    )
    assert families[-1].description.endswith(
        "sin and cos of each coordinate and sin and cos of 2x_i and 3x_i (38 terms)"
    )


def test_point_at_the_origin_is_refused_with_one_clear_error(canonical):
    fam = LibraryFamily(canonical, 2, trig=False, distance_powers=(-1,))
    good = _periapsis(0.1, 0.0)
    with pytest.raises(ValueError, match=r"trajectories: 1 record\(s\) put point 2 at the origin"):
        fam.check_states(np.array([good, [1.0, 0.5, 0.0, 0.0]]))
    with pytest.raises(ValueError, match=r"put points 1 and 2 at the same place"):
        fam.check_states(np.array([[0.3, 0.4, 0.3, 0.4]]))
    fam.check_states(good[None])


def test_the_search_passes_over_a_library_singular_on_the_records(canonical):
    """pr.learn's search skips a library whose terms are singular on some record (a point at
    the origin under |z|^-1) and goes on; the library asked for by name still refuses them."""
    from types import SimpleNamespace

    from poisson_rs.learn.api import _library_applies

    dist = LibraryFamily(canonical, 2, trig=False, distance_powers=(-1,))
    trig = LibraryFamily(canonical, 2)
    good = _periapsis(0.1, 0.0)
    at_origin = SimpleNamespace(train=[np.array([good])], test=[np.array([[0.0, 0.0, 1.0, 0.5]])])
    assert not _library_applies(dist, at_origin, verbose=False)
    assert _library_applies(trig, at_origin, verbose=False)  # defined everywhere
    assert _library_applies(dist, SimpleNamespace(train=[good[None]], test=[]), verbose=False)


def test_fit_recovers_kepler(canonical):
    """Planar Kepler H = |p|²/2 − 1/|q| from exact records (3 orbits of e = 0.1, 0.2, 0.3 × 41
    records, h = 0.1): every coefficient of poly2+dist^-1 within 1e-6 of the true one (½ on p1²,
    p2², −1 on |q|^−1, 0 elsewhere), and the error at T = 100 from each training start and an
    unseen orbit within 2× of the true H's through the same integrator (benches/library_kepler.py
    runs pr.learn's whole search)."""
    h = 0.1
    kepler = pr.with_hamiltonian(canonical, "0.5*(x3**2 + x4**2) - (x1**2 + x2**2)**(-0.5)")
    starts = np.array([_periapsis(e, 1.3 * k) for k, e in enumerate((0.1, 0.2, 0.3))])
    trajs = list(np.asarray(pr.reference_solution(kepler, starts, np.arange(41) * h)))
    data = prepare(trajs, h, None, seed=0, system=canonical)
    fam = LibraryFamily(canonical, 2, trig=False, distance_powers=(-1,))
    fit = fit_structure_hamiltonian(data, canonical, 2, family=fam)
    learned = dict(zip(fit.family.exponents, fit.theta, strict=True))
    truth = {(0, 0, 2, 0): 0.5, (0, 0, 0, 2): 0.5, ("radius", -1, 0): -1.0}
    for key in fam.exponents:
        assert abs(learned.get(key, 0.0) - truth.get(key, 0.0)) <= 1e-6, key
    x0 = np.vstack([starts, [0.9, 0.3, -0.3, 1.0]])
    ref = np.asarray(pr.reference_solution(kepler, x0, [0.0, 100.0]))[:, -1]
    true = kepler.taylor_integrator(fam.order, tol=NEWTON_TOL, max_iter=NEWTON_MAX_ITER)
    end_true = pr.integrate(true, x0, h, 1000, every=1000)[:, -1]
    end_learned = pr.integrate(fit.stepper, x0, h, 1000, every=1000)[:, -1]
    err_true = np.max(np.abs(end_true - ref), axis=1)
    err_learned = np.max(np.abs(end_learned - ref), axis=1)
    # Over the states: on one the true H's own error may happen to be small (a cancellation).
    assert err_learned.max() <= 2.0 * err_true.max(), (err_learned, err_true)


# Functions of linear forms: exp(±x_i), exp(x_i − x_j), sin and cos of x_i − x_j.


def test_the_linear_forms_are_the_coordinates_and_their_differences():
    assert linear_forms(3, "trigdiff") == [(1, -1, 0), (1, 0, -1), (0, 1, -1)]
    exps = linear_forms(3, "exp")
    assert exps[:6] == [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]
    # Every ordered pair: exp(x1 − x2) and exp(x2 − x1) are different functions.
    assert sorted(exps[6:]) == sorted(
        tuple(int(i == a) - int(i == b) for i in range(3))
        for a in range(3)
        for b in range(3)
        if a != b
    )
    assert len(set(exps)) == len(exps) == 2 * 3 + 3 * 2
    assert linear_forms(2, "harmonics") == [(2, 0), (3, 0), (0, 2), (0, 3)]
    with pytest.raises(ValueError, match="kind must be 'exp', 'trigdiff' or 'harmonics'"):
        linear_forms(3, "tan")


def test_linear_form_terms_value_and_gradient_match_autograd(canonical):
    torch = pytest.importorskip("torch")
    fam = LibraryFamily(canonical, 1, trig=False, exponentials=True, differences=True)
    forms = [m for m, k in enumerate(fam.exponents) if isinstance(k[1], tuple)]
    assert len(forms) == len(fam) - 4 == (8 + 12) + 2 * 6
    assert fam.name == "poly1+exp+trigdiff"
    x = np.random.default_rng(11).normal(size=(7, 4))
    xt = torch.tensor(x, requires_grad=True)
    grads = fam.gradients(x)
    for m in forms:
        f, ell = fam.exponents[m]
        phi = getattr(torch, f)(xt @ torch.tensor(ell, dtype=torch.float64))
        (grad,) = torch.autograd.grad(phi.sum(), xt)
        np.testing.assert_allclose(grads[:, :, m], grad.numpy(), rtol=1e-13, atol=1e-13)
        # The text the learned system steps is the same function.
        value = fam.system(np.eye(len(fam))[m]).hamiltonian(x)
        np.testing.assert_allclose(value, phi.detach().numpy(), rtol=1e-13, atol=1e-13)
    exp_q1_q2 = fam.exponents.index(("exp", (1, -1, 0, 0)))
    assert fam.text(np.eye(len(fam))[exp_q1_q2]) == "(1.0)*exp(x1 - x2)"
    assert fam.text(np.eye(len(fam))[fam.exponents.index(("exp", (0, -1, 0, 0)))]) == (
        "(1.0)*exp(-x2)"
    )


def test_linear_form_keys_read_back_from_json_and_bad_ones_are_refused(canonical):
    fam = LibraryFamily(canonical, 2, trig=False, exponentials=True)
    kept = fam.restrict([["exp", [1, -1, 0, 0]], [0, 0, 2, 0]])
    assert kept.exponents == [("exp", (1, -1, 0, 0)), (0, 0, 2, 0)]
    assert kept.name == "poly2+exp" and kept.exponentials and not kept.differences
    with pytest.raises(ValueError, match="keys must be terms of the library poly2\\+exp"):
        fam.restrict([("exp", (2, 0, 0, 0))])
    with pytest.raises(ValueError, match="keys must be terms of the library poly2\\+exp"):
        fam.restrict([("sin", (1, -1, 0, 0))])


def _toda_pair() -> str:
    """The periodic Toda pair on (q1, q2, p1, p2): H = |p|²/2 + exp(q1 − q2) + exp(q2 − q1)."""
    return "0.5*(x3**2 + x4**2) + exp(x1 - x2) + exp(x2 - x1)"


def _recovery(system, fam, starts, h, n_records, truth, horizon_steps):
    """Fits ``fam`` to exact records of ``system`` from ``starts``; asserts every coefficient
    within 1e-6 of ``truth`` (0 for the others: on exact records the spare terms absorb a little
    of the integrator's truncation error, so the fit may keep them, near zero) and the error after
    ``horizon_steps`` steps (the largest over the starts and an unseen state) within 2× of the
    true H's through the same integrator."""
    trajs = list(np.asarray(pr.reference_solution(system, starts, np.arange(n_records) * h)))
    data = prepare(trajs, h, None, seed=0, system=fam.structure)
    fit = fit_structure_hamiltonian(data, fam.structure, fam.degree, family=fam)
    learned = dict(zip(fit.family.exponents, fit.theta, strict=True))
    for key in fam.exponents:
        assert abs(learned.get(key, 0.0) - truth.get(key, 0.0)) <= 1e-6, (key, learned)
    x0 = np.vstack([starts, starts[0] * 0.9 + 0.05])
    t_end = horizon_steps * h
    ref = np.asarray(pr.reference_solution(system, x0, [0.0, t_end]))[:, -1]
    true = system.taylor_integrator(fam.order, tol=NEWTON_TOL, max_iter=NEWTON_MAX_ITER)
    every = horizon_steps
    end_true = pr.integrate(true, x0, h, horizon_steps, every=every)[:, -1]
    end_learned = pr.integrate(fit.stepper, x0, h, horizon_steps, every=every)[:, -1]
    err_true = np.max(np.abs(end_true - ref), axis=1)
    err_learned = np.max(np.abs(end_learned - ref), axis=1)
    # Over the states: on one the true H's own error may happen to be small (a cancellation).
    assert err_learned.max() <= 2.0 * err_true.max(), (err_learned, err_true)


def test_fit_recovers_a_toda_pair(canonical):
    """The periodic Toda pair from exact records (3 × 41, h = 0.1): poly2+exp's 34 coefficients
    fit the true 4 (½ on p1², p2²; 1 on exp(q1 − q2) and exp(q2 − q1)), each within 1e-6 (the other
    30 within 1e-6 of 0), and the rollout error at T = 10 within 2× of the true H's through the
    same integrator (T = 100 and pr.learn's whole search: benches/library_linear_forms.py)."""
    system = pr.with_hamiltonian(canonical, _toda_pair())
    fam = LibraryFamily(canonical, 2, trig=False, exponentials=True)
    assert len(fam) == 14 + 8 + 12
    starts = np.array([[0.0, 0.5, 0.3, -0.2], [0.4, -0.3, -0.5, 0.1], [-0.2, 0.1, 0.6, 0.5]])
    truth = {
        (0, 0, 2, 0): 0.5,
        (0, 0, 0, 2): 0.5,
        ("exp", (1, -1, 0, 0)): 1.0,
        ("exp", (-1, 1, 0, 0)): 1.0,
    }
    _recovery(system, fam, starts, 0.1, 41, truth, 100)


def test_fit_recovers_coupled_pendula(canonical):
    """Two pendula coupled by a spring of the angle difference, H = |p|²/2 − 2 cos q1 − cos q2
    − ½ cos(q1 − q2): poly2+trig+trigdiff's 34 coefficients within 1e-6 of the true 5 (and of 0),
    and the rollout error at T = 10 within 2× of the true H's."""
    system = pr.with_hamiltonian(
        canonical, "0.5*(x3**2 + x4**2) - 2*cos(x1) - cos(x2) - 0.5*cos(x1 - x2)"
    )
    fam = LibraryFamily(canonical, 2, differences=True)
    assert len(fam) == 14 + 8 + 12
    starts = np.array([[0.5, -0.3, 0.2, 0.4], [-0.8, 0.6, 0.1, -0.3], [0.2, 1.0, -0.4, 0.0]])
    truth = {
        (0, 0, 2, 0): 0.5,
        (0, 0, 0, 2): 0.5,
        ("cos", 0): -2.0,
        ("cos", 1): -1.0,
        ("cos", (1, -1, 0, 0)): -0.5,
    }
    _recovery(system, fam, starts, 0.1, 41, truth, 100)


def test_learn_finds_lotka_volterra_in_log_coordinates():
    """ẋ = x(1 − y), ẏ = y(x − 1) in (q, p) = (ln x, ln y) is canonical with
    H = p − exp(p) + q − exp(q): no polynomial or trigonometric family reaches the noise level of
    exact records (3 × 41, h = 0.1); poly2+exp does, keeping its 4 true terms of 11 with the true
    coefficients to 1e-6 (H is fixed up to a constant on a symplectic bracket, for which the
    library has no term)."""
    canonical = pr.PolynomialPoissonSystem(
        pr.PolynomialBivector(2, {(0, 1): "1"}), "x1**2", name="canonical (q, p)"
    )
    system = pr.with_hamiltonian(canonical, "x2 - exp(x2) + x1 - exp(x1)")
    h, starts = 0.1, np.array([[0.5, 0.0], [-0.4, 0.3], [0.2, -0.7]])
    trajs = list(np.asarray(pr.reference_solution(system, starts, np.arange(41) * h)))
    stepper, report = pr.learn(trajs, h, structure=canonical, seed=0, progress=False)
    families = [c.family for c in report.candidates]
    assert families == ["poly2", "poly3", "poly4", "poly2+trig", "poly3+trig", "poly2+exp"]
    assert report.explained and report.kept.one_step <= report.threshold
    assert all(c.one_step > 1000 * report.kept.one_step for c in report.candidates[:-1])
    # Exactly the true terms: the spare ones only absorb truncation error far below the
    # records' noise bound, and a spare exp(±x_i) would grow without bound off the records.
    fit = report.kept.fit
    learned = dict(zip(fit.family.exponents, fit.theta, strict=True))
    truth = {(1, 0): 1.0, (0, 1): 1.0, ("exp", (1, 0)): -1.0, ("exp", (0, 1)): -1.0}
    assert set(learned) == set(truth)
    for key, value in truth.items():
        assert abs(learned[key] - value) <= 1e-6, key
    assert "exp(x1)" in report.hamiltonian_text and "exp(x2)" in report.hamiltonian_text
    # The learned stepper conserves the true H's level set to the fit's accuracy over T = 100.
    roll = pr.integrate(stepper, starts, h, 1000)
    energy = np.asarray(system.hamiltonian(roll.reshape(-1, 2))).reshape(roll.shape[:2])
    assert np.max(np.abs(energy - energy[:, :1])) < 1e-5


def test_records_where_an_exponential_overflows_are_refused_or_passed_over(canonical):
    """exp(ℓ·x) overflows past ℓ·x ≈ 709.8: a record there is refused by name (the largest
    argument, here x3 − x2 = 705.5) when the library is asked for, and pr.learn's search passes
    over the library, as over a singular one."""
    from types import SimpleNamespace

    from poisson_rs.learn.api import _library_applies

    fam = LibraryFamily(canonical, 2, trig=False, exponentials=True)
    fam.check_states(np.array([[1.0, -2.0, 300.0, 0.5]]))  # e^300 is a float
    far = np.array([[1.0, 0.0, 0.5, 0.5], [0.0, -705.0, 0.5, 0.5]])
    message = (
        r"trajectories: 1 record\(s\) give the term library poly2\+exp's exp\(-x2 \+ x3\) an "
        r"argument above 700, e.g. 705.5 in the state \[0.0, -705.0, 0.5, 0.5\]"
    )
    with pytest.raises(ValueError, match=message):
        fam.check_states(far)
    records = SimpleNamespace(train=[far], test=[])
    assert not _library_applies(fam, records, verbose=False)
    assert _library_applies(LibraryFamily(canonical, 2, differences=True), records, verbose=False)


# Products of coordinates with sines and cosines, x_j sin x_i and x_j cos x_i.


def test_product_terms_value_and_gradient_match_autograd(pendulum):
    torch = pytest.importorskip("torch")
    fam = LibraryFamily(pendulum.base, 1, products=True)
    products = [m for m, k in enumerate(fam.exponents) if k[0] in ("xsin", "xcos")]
    assert fam.name == "poly1+trig+xtrig" and len(products) == 2 * 3 * 3
    x = np.random.default_rng(12).normal(size=(7, 3))
    xt = torch.tensor(x, requires_grad=True)
    grads = fam.gradients(x)
    for m in products:
        f, j, i = fam.exponents[m]
        phi = xt[:, j] * getattr(torch, f[1:])(xt[:, i])
        (grad,) = torch.autograd.grad(phi.sum(), xt)
        np.testing.assert_allclose(grads[:, :, m], grad.numpy(), rtol=1e-13, atol=1e-13)
        value = fam.system(np.eye(len(fam))[m]).hamiltonian(x)
        np.testing.assert_allclose(value, phi.detach().numpy(), rtol=1e-13, atol=1e-13)
    u_cos_u = fam.exponents.index(("xcos", 0, 0))
    assert fam.text(np.eye(len(fam))[u_cos_u]) == "(1.0)*u*cos(u)"
    kept = fam.restrict([["xsin", 2, 1], (1, 0, 0)])
    assert kept.exponents == [("xsin", 2, 1), (1, 0, 0)] and kept.products
    with pytest.raises(ValueError, match="keys must be terms of the library poly1\\+trig\\+xtrig"):
        fam.restrict([("xsin", 3, 0)])


def test_fit_recovers_a_pendulum_on_a_spring(canonical):
    """A pendulum whose gravity term a spring's stretch q2 scales, H = |p|²/2 − (1 + ½q2) cos q1
    + q2²: the product q2 cos q1 is in no other library. poly2+trig+xtrig's 54 coefficients fit
    the true 5 within 1e-6 (the other 49 within 1e-6 of 0), and the rollout error at T = 10 is
    within 2× of the true H's through the same integrator."""
    system = pr.with_hamiltonian(canonical, "0.5*(x3**2 + x4**2) - (1 + 0.5*x2)*cos(x1) + x2**2")
    fam = LibraryFamily(canonical, 2, products=True)
    assert len(fam) == 14 + 8 + 32
    assert fam.name in [f.name for f in library_families(canonical, None, 2)]
    starts = np.array([[0.5, -0.3, 0.2, 0.4], [-0.8, 0.6, 0.1, -0.3], [0.2, 0.4, -0.4, 0.0]])
    truth = {
        (0, 0, 2, 0): 0.5,
        (0, 0, 0, 2): 0.5,
        (0, 2, 0, 0): 1.0,
        ("cos", 0): -1.0,
        ("xcos", 1, 0): -0.5,
    }
    _recovery(system, fam, starts, 0.1, 41, truth, 100)


# Harmonics: sin and cos of 2x_i and 3x_i.


def test_fit_recovers_a_torsion_potential():
    """A rotor with a dihedral-angle potential, H = p²/2 − cos q + 0.4 cos 2q − 0.2 sin 3q (three
    harmonics, as a molecular torsion term): poly2+trig+harmonics's 17 coefficients fit the true 4
    within 1e-6 (the others within 1e-6 of 0), the error at T = 10 within 2× of the true H's through
    the same integrator; the harmonic terms' values and gradients equal autograd's."""
    torch = pytest.importorskip("torch")
    canonical = pr.PolynomialPoissonSystem(
        pr.PolynomialBivector(2, {(0, 1): "1"}), "x1**2", name="canonical (q, p)"
    )
    fam = LibraryFamily(canonical, 2, harmonics=True)
    assert fam.name == "poly2+trig+harmonics" and len(fam) == 5 + 4 + 8
    x = np.random.default_rng(13).normal(size=(7, 2))
    xt = torch.tensor(x, requires_grad=True)
    grads = fam.gradients(x)
    for m, key in enumerate(fam.exponents):
        if not (isinstance(key[0], str) and isinstance(key[1], tuple)):
            continue
        phi = getattr(torch, key[0])(xt @ torch.tensor(key[1], dtype=torch.float64))
        (grad,) = torch.autograd.grad(phi.sum(), xt)
        np.testing.assert_allclose(grads[:, :, m], grad.numpy(), rtol=1e-13, atol=1e-13)
        value = fam.system(np.eye(len(fam))[m]).hamiltonian(x)
        np.testing.assert_allclose(value, phi.detach().numpy(), rtol=1e-13, atol=1e-13)
    system = pr.with_hamiltonian(canonical, "0.5*x2**2 - cos(x1) + 0.4*cos(2*x1) - 0.2*sin(3*x1)")
    starts = np.array([[0.5, 0.3], [-1.0, 0.6], [2.0, -0.4]])
    truth = {(0, 2): 0.5, ("cos", 0): -1.0, ("cos", (2, 0)): 0.4, ("sin", (3, 0)): -0.2}
    _recovery(system, fam, starts, 0.1, 41, truth, 100)
