"""The structure protocol and the stepper protocol: one name per job on every structure, a
stepper written outside the package through every tool, and systems read by kind."""

from __future__ import annotations

import functools
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.structures.charged_particle import ChargedParticle
from poisson_rs.studies.stability import stability_map
from poisson_rs.studies.workprecision import Scene, sweep


def _pendulum() -> Any:
    # PNN's extended pendulum on (u, v, r): g = e(2), ω_uv = −1; H = u²/2 + v²/2.
    c = np.zeros((3, 3, 3))
    c[0, 2, 1], c[2, 0, 1] = 2.0, -2.0  # {u, r} = −2v
    c[1, 2, 0], c[2, 1, 0] = -2.0, 2.0  # {v, r} = 2u
    cocycle = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    return pr.affine_poisson_system(c, cocycle, {(2, 0, 0): 0.5, (0, 2, 0): 0.5})


@functools.cache
def _systems() -> dict[str, Any]:
    """One system of each structure, built when a test first asks (two need sympy)."""
    return {
        "rigid_body": pr.RigidBody(),
        "heavy_top": pr.HeavyTop(),
        "lotka_volterra": pr.lotka_volterra([[0, 1], [-1, 0]], [1, 2]),
        "affine": _pendulum(),
        "nambu": pr.PolynomialPoissonSystem(
            pr.PolynomialBivector.nambu("x1**2 + x2**2 + x3**3/3"), "x1**2/2 + x2**2 + x3**2/3"
        ),
        "charged_particle": ChargedParticle("1 + x1**2/4"),
    }


KINDS = ("rigid_body", "heavy_top", "lotka_volterra", "affine", "nambu", "charged_particle")


@pytest.fixture(params=KINDS, ids=KINDS)
def system(request: pytest.FixtureRequest) -> Any:
    return _systems()[request.param]


def test_every_structure_implements_the_protocol(system: Any) -> None:
    assert isinstance(system, pr.PoissonSystem)
    x = system.demo_states
    assert x.shape == (2, system.dim) and system.in_domain(x).all()
    pi = system.bivector(x)
    np.testing.assert_allclose(pi, -np.swapaxes(pi, -1, -2), atol=1e-14)
    # ẋ = π(x)∇H(x), with ∇H by central differences (an independent oracle of the field).
    eps = 1e-6
    grad = np.stack(
        [
            (system.hamiltonian(x + eps * e) - system.hamiltonian(x - eps * e)) / (2 * eps)
            for e in np.eye(system.dim)
        ],
        axis=-1,
    )
    np.testing.assert_allclose(
        system.vector_field(x), np.einsum("nij,nj->ni", pi, grad), rtol=1e-7, atol=1e-7
    )
    assert pr.system_from_dict(system.to_dict()).to_dict() == system.to_dict()


def test_single_names_build_every_listed_method(system: Any) -> None:
    """classical_methods lists exactly what classical builds, and each one runs."""
    x0 = system.demo_states
    for name in pr.classical_methods(system):
        traj = pr.integrate(pr.classical(system, name), x0, 0.01, 4)
        assert traj.shape == (2, 5, system.dim) and np.isfinite(traj).all(), name
    with pytest.raises(ValueError, match="valid names"):
        pr.classical(system, "no-such-method")
    for chart in system.taylor_charts()[:1]:
        stepper = pr.taylor_integrator(system, 3, chart)
        assert np.isfinite(pr.integrate(stepper, x0, 0.01, 4)).all()
    with pytest.raises(ValueError, match="not available"):
        pr.taylor_integrator(system, 3, "no-such-chart")


def test_taylor_matches_the_reference_at_its_order(system: Any) -> None:
    """Taylor-HJ m = 3 (order 4) against the structure's own DOP853 reference: halving h
    divides the error at T = 0.5 by about 2⁴."""
    x0 = system.demo_states[:1] * 0.5 if system.kind != "log_canonical" else system.demo_states[:1]
    stepper = pr.taylor_integrator(system, 3)
    ref = pr.reference_solution(system, x0, [0.5])[:, -1]
    errs = [np.abs(pr.integrate(stepper, x0, 0.5 / n, n)[:, -1] - ref).max() for n in (8, 16)]
    assert 2**3.4 < errs[0] / errs[1] < 2**4.6, errs


def test_reference_solution_and_newton_defaults_are_one(system: Any) -> None:
    x0 = system.demo_states
    out = pr.reference_solution(system, x0, [0.0, 0.1])
    np.testing.assert_allclose(out[:, 0], x0)
    for stepper in (pr.taylor_integrator(system, 1), pr.classical(system, "midpoint")):
        assert (stepper.tol, stepper.max_iter) == (pr.NEWTON_TOL, pr.NEWTON_MAX_ITER)


def test_not_a_system_is_refused_naming_what_is_missing() -> None:
    with pytest.raises(TypeError, match="Poisson system"):
        pr.taylor_integrator(object(), 3)
    with pytest.raises(TypeError, match="Poisson system"):
        pr.classical_methods("rigid body")
    with pytest.raises(TypeError, match="Poisson system"):
        pr.reference_solution(42, [1.0, 2.0, 3.0], [0.0])


def test_old_names_are_aliases_with_the_same_bits() -> None:
    lv = _systems()["lotka_volterra"]
    x0 = np.array([[1.0, 0.8], [1.0, 1.2]])
    new = pr.integrate(pr.taylor_integrator(lv, 3), x0, 0.1, 50)
    np.testing.assert_array_equal(pr.integrate(pr.log_canonical_taylor(lv, 3), x0, 0.1, 50), new)
    new = pr.integrate(pr.classical(lv, "log_splitting4"), x0, 0.1, 50)
    old = pr.integrate(pr.log_canonical_classical(lv, "log_splitting4"), x0, 0.1, 50)
    np.testing.assert_array_equal(old, new)
    affine = _systems()["affine"]
    x0 = affine.demo_states
    np.testing.assert_array_equal(
        pr.integrate(pr.affine_taylor(affine, 3), x0, 0.1, 20),
        pr.integrate(pr.taylor_integrator(affine, 3), x0, 0.1, 20),
    )


def test_studies_pick_the_charts_a_system_has() -> None:
    """A rigid body plus a cubic term is on so(3) but has no Cayley series: the studies use exp."""
    h = pr.Polynomial({(2, 0, 0): 1 / 3, (0, 2, 0): 1 / 4, (0, 0, 2): 1 / 5, (1, 1, 1): 0.03})
    system = pr.LiePoissonSystem(pr.LieAlgebra.so3(), h)
    assert system.taylor_charts() == ("exp",)
    rows = stability_map(system, step_sizes=(0.1,), radii=(1.0,), horizon=1.0)
    assert {r["method"] for r in rows} >= {"taylor3-exp", "taylor5-exp", "rk4"}


# --- a stepper written outside the package -------------------------------------------------------


class ExplicitEuler:
    """The simplest user stepper: explicit Euler on any system's vector field, in NumPy."""

    def __init__(self, system: Any) -> None:
        self.system = system
        self.name = "euler"
        self.order = 1

    @property
    def dim(self) -> int:
        return int(self.system.dim)

    def rollout(
        self, x0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        out = np.empty((len(x0), n_steps // every + 1, self.dim))
        x = x0.copy()
        out[:, 0] = x
        for k in range(1, n_steps + 1):
            x = x + h * self.system.vector_field(x)
            if k % every == 0:
                out[:, k // every] = x
        return out, {}


def test_a_user_stepper_runs_through_integrate() -> None:
    body = pr.RigidBody()
    traj, info = pr.integrate(ExplicitEuler(body), [1.0, 1.0, 2.0], 0.001, 100, return_info=True)
    exact = pr.exact_solution(body, [1.0, 1.0, 2.0], [0.1])[-1]
    assert 1e-6 < np.abs(traj[-1] - exact).max() < 1e-3  # first order at h = 1e-3
    assert info.converged.all() and np.isnan(info.max_residual).all()  # unknown, not 0
    assert np.isfinite(info.step_angle).all()  # the system's rate, known


def test_a_user_stepper_that_breaks_the_contract_is_named() -> None:
    class Wrong(ExplicitEuler):
        def rollout(self, x0: np.ndarray, h: float, n_steps: int, every: int) -> Any:
            return np.zeros((1, 1, 1)), {}

    with pytest.raises(TypeError, match=r"Wrong.*rollout must return"):
        pr.integrate(Wrong(pr.RigidBody()), [1.0, 1.0, 2.0], 0.1, 3)
    with pytest.raises(TypeError, match="integrator"):
        pr.integrate(object(), [1.0, 1.0, 2.0], 0.1, 3)


def test_a_user_stepper_failure_is_reported_not_hidden() -> None:
    body = pr.RigidBody()
    with (
        np.errstate(over="ignore", invalid="ignore"),
        pytest.warns(RuntimeWarning, match="1 of 1 trajectories failed"),
    ):
        _, info = pr.integrate(ExplicitEuler(body), [1e200, 1e200, 1e200], 1.0, 5, return_info=True)
    assert not info.converged[0] and info.failure_code[0] == 3


def test_a_user_stepper_runs_through_chart_stability_and_select() -> None:
    body = pr.RigidBody()
    euler = ExplicitEuler(body)
    scene = Scene("two", body, np.array([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]]), 1.0)
    from poisson_rs.studies.workprecision import Method

    rows = sweep([scene], [Method("euler", "given", euler)], steps=(50, 100), repeats=False)
    errs = [r["error_T"] for r in rows if r["method"] == "euler"]
    assert len(errs) == 2 and errs[1] < errs[0]  # it converges
    rows = stability_map(
        body, step_sizes=(0.01, 0.5), radii=(1.0,), horizon=1.0, methods={"euler": lambda: euler}
    )
    assert {r["method"] for r in rows} == {"euler"}
    _, _, report = pr.select(
        body, [1.0, 1.0, 2.0], T=1.0, target=1e-1, models=[euler], budget_s=5.0
    )
    assert "learned:euler" in str(report)


# --- the fifth structure, added through the protocol alone ----------------------------------------


def test_charged_particle_taylor_orders_and_energy() -> None:
    particle = _systems()["charged_particle"]
    x0 = np.array([[0.3, -0.2, 1.0, 0.5]])
    ref = particle.reference_solution(x0, [1.0])[:, -1]
    for m, order in ((1, 2), (3, 4)):
        stepper = pr.taylor_integrator(particle, m)
        errs = [np.abs(pr.integrate(stepper, x0, 1.0 / n, n)[:, -1] - ref).max() for n in (8, 16)]
        assert abs(np.log2(errs[0] / errs[1]) - order) < 0.4, (m, errs)
    # Symplectic: the energy error stays bounded over a long run (no drift).
    traj = pr.integrate(pr.taylor_integrator(particle, 3), x0, 0.1, 5000, every=50)
    dh = np.abs(particle.hamiltonian(traj) - particle.hamiltonian(x0)[:, None])
    assert dh.max() < 1e-4 and dh[:, -20:].max() < 2 * dh[:, :20].max() + 1e-12
    assert particle.casimirs(x0) is None  # symplectic: none (n/a)


def test_charged_particle_in_space_needs_a_divergence_free_field() -> None:
    with pytest.raises(ValueError, match="divergence-free"):
        ChargedParticle(["x1", "0", "0"])
    particle = ChargedParticle(["0", "0", "1 + x1**2"])
    x0 = np.array([[0.1, 0.2, 0.0, 1.0, 0.0, 0.3]])
    ref = particle.reference_solution(x0, [0.5])[:, -1]
    got = pr.integrate(pr.taylor_integrator(particle, 5), x0, 0.05, 10)[:, -1]
    assert np.abs(got - ref).max() < 1e-8
    # ẋ = v and v̇ = v × B for H = |v|²/2.
    f = particle.vector_field(x0)[0]
    v, b = x0[0, 3:], np.array([0.0, 0.0, 1.0 + 0.01])
    np.testing.assert_allclose(f, np.concatenate([v, np.cross(v, b)]), atol=1e-14)


def test_charged_particle_pickles_and_reads_from_a_scene(tmp_path: Path) -> None:
    particle = _systems()["charged_particle"]
    stepper = pr.taylor_integrator(particle, 3)
    x0 = np.array([[0.3, -0.2, 1.0, 0.5]])
    again = pickle.loads(pickle.dumps(stepper))
    np.testing.assert_array_equal(
        pr.integrate(again, x0, 0.1, 10), pr.integrate(stepper, x0, 0.1, 10)
    )
    scene = tmp_path / "particle.toml"
    scene.write_text(
        '[system]\nkind = "charged_particle"\nfield = "1 + x1**2/4"\n'
        "[states]\npoints = [[0.3, -0.2, 1.0, 0.5]]\n[steps]\nh = 0.1\nhorizon = 1.0\n"
        "[target]\nerror = 1e-3\n"
    )
    from poisson_rs.scenes import load_scene

    assert load_scene(scene).lie_system == particle
    scene.write_text(scene.read_text().replace("field =", "feld ="))
    with pytest.raises(ValueError, match=r"system\.feld"):
        load_scene(scene)


def test_unknown_kinds_are_refused_naming_the_kinds() -> None:
    with pytest.raises(ValueError, match=r"charged_particle.*log_canonical"):
        pr.system_from_dict({"kind": "no-such"})


def test_dop853_gives_up_on_one_trajectory_the_same_way_on_every_structure(system: Any) -> None:
    """A state DOP853 cannot reach T from (|x| far too large for its step budget) is NaN from
    there on and reported as failed; the other trajectory is kept (it never raises out of
    integrate unless asked to)."""
    x0 = np.array([system.demo_states[0], system.demo_states[0] * 1e8])
    stepper = pr.classical(system, "dop853")
    with pytest.warns(RuntimeWarning, match="1 of 2 trajectories failed"):
        traj, info = pr.integrate(stepper, x0, 0.1, 10, return_info=True)
    assert info.converged.tolist() == [True, False] and info.failure_code[1] == 1
    assert np.isfinite(traj[0]).all() and np.isnan(traj[1, 1:]).all()
    with pytest.raises(RuntimeError, match="1 of 2"):
        pr.integrate(stepper, x0, 0.1, 10, on_failure="raise")


def test_an_unreachable_reference_is_one_line_on_the_command_line(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from poisson_rs.cli import main

    scene = Path(__file__).parent.parent / "scenes" / "lotka_volterra_pnn.toml"
    assert main(["select", str(scene), "--T", "1e5"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no reference: DOP853" in err


def test_select_by_casimir_on_a_system_without_one_says_what_works() -> None:
    particle = _systems()["charged_particle"]
    with pytest.raises(ValueError, match=r"no Casimir is known.*choose metric='error' or 'energy'"):
        pr.select(particle, [0.3, -0.2, 1.0, 0.5], T=1.0, target=1e-6, metric="casimir")


def test_the_fifth_structure_runs_through_every_tool(tmp_path: Path) -> None:
    """The shipped charged-particle scene: demo, stability and select on the command line,
    with nothing outside its module knowing the structure."""
    from poisson_rs.cli import main

    scene = Path(__file__).parent.parent / "scenes" / "charged_particle.toml"
    argv = ["demo", "--scene", str(scene), "--steps", "20", "--out", str(tmp_path / "d")]
    assert main(argv) == 0
    assert (tmp_path / "d" / "metrics.csv").read_text().count("taylor5-canonical") >= 3
    argv = ["stability", str(scene), "--quick", "--horizon", "1", "--no-progress"]
    assert main([*argv, "--out", str(tmp_path / "s")]) == 0
    out = tmp_path / "select.json"
    assert main(["select", str(scene), "--T", "1", "--budget", "1", "--json", str(out)]) == 0
    assert "taylor5-canonical" in out.read_text()
