"""``pr.learn(..., structure=...)`` on the structures other than Lie–Poisson: H fitted through the
structure's own Taylor-HJ integrator, from exact trajectories of a known system (affine: PNN's
extended pendulum; polynomial bivector: the cubic Nambu bracket; the charged particle in a
polynomial B), compared by vector fields (H is identifiable only up to Casimirs and a
constant), and bad input refused with one clear error."""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.scenes import load_scene
from poisson_rs.structures.charged_particle import charged_particle
from poisson_rs.structures.polynomial import PolynomialPoissonSystem

SCENES = Path(__file__).resolve().parents[1] / "scenes"
H = 0.1
RECORDS = 41  # training records per trajectory
LONG = 400  # steps of the longer-horizon rollout


def _system(name: str) -> Any:
    if name == "charged_particle":
        # A polynomial B and a polynomial H with a potential: ẋ = v, v̇ = B v^⊥ − ∇φ.
        return charged_particle("1 + x1**2/4", "x3**2/2 + x4**2/2 + x1**2/8 + x2**2/8")
    return load_scene(SCENES / f"{name}.toml").system


def _starts(system: Any, count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = _points(system)
    return pts[rng.integers(len(pts), size=count)] + 0.1 * rng.normal(size=(count, system.dim))


def _points(system: Any) -> np.ndarray:
    return {
        3: np.array([[0.8, -0.5, 2.0], [0.0, 1.0, 0.5], [1.2, 0.3, 1.0]])
        if system.kind == "affine"
        else np.array([[0.3, 0.5, -0.4], [0.1, -0.6, 0.3]]),
        4: np.array([[0.3, -0.2, 1.0, 0.5], [0.0, 0.0, 0.5, 0.5], [1.0, 0.5, -0.3, 0.8]]),
    }[system.dim]


# name: (degree of the true H, Taylor order fitted through)
CASES = {"extended_pendulum": (4, 3), "nambu_cubic": (2, 3), "charged_particle": (2, 5)}


@cache
def _learned(name: str) -> tuple[Any, Any, Any, np.ndarray]:
    """(true system, stepper, report, held-out starts): learned from 6 exact trajectories."""
    system = _system(name)
    trajs = system.reference_solution(_starts(system, 6, 0), np.arange(RECORDS) * H)
    degree, order = CASES[name]
    stepper, report = pr.learn(
        trajs, H, structure=system, mode="hamiltonian", degree=degree, order=order
    )
    return system, stepper, report, _starts(system, 3, 1)


@pytest.mark.parametrize("name", list(CASES))
def test_learned_vector_field_matches_the_true_one_at_held_out_states(name: str) -> None:
    system, _, report, starts = _learned(name)
    held = system.reference_solution(starts, np.arange(RECORDS) * H).reshape(-1, system.dim)
    a = report.system.vector_field(held)
    b = system.vector_field(held)
    rel = np.max(np.linalg.norm(a - b, axis=1)) / np.max(np.linalg.norm(b, axis=1))
    assert rel <= 1e-6, rel


@pytest.mark.parametrize("name", list(CASES))
def test_learned_rollout_within_2x_of_the_true_h_through_the_same_integrator(name: str) -> None:
    system, stepper, report, starts = _learned(name)
    times = np.arange(LONG + 1) * H
    ref = system.reference_solution(starts, times)
    true = pr.integrate(pr.taylor_integrator(system, report.kept.order), starts, H, LONG)
    learned = pr.integrate(stepper, starts, H, LONG)
    e_true = float(np.max(np.abs(true - ref)))
    e_learned = float(np.max(np.abs(learned - ref)))
    assert e_learned <= 2.0 * e_true, (e_learned, e_true)


@pytest.mark.parametrize("name", list(CASES))
def test_report_names_the_family_and_the_gauge(name: str) -> None:
    system, stepper, report, starts = _learned(name)
    text = str(report)
    assert report.mode == "hamiltonian" and report.kept.kept
    assert report.kept.family == f"poly{CASES[name][0]}"
    assert "H family: a polynomial in" in text and "gauge" in text
    assert report.hamiltonian_text and report.gauge
    assert report.system.kind == system.kind
    # The returned stepper is the learned system's integrator: pr.integrate takes both.
    out = pr.integrate(stepper, starts, H, 5)
    assert out.shape == (3, 6, system.dim) and np.isfinite(out).all()


def test_learned_stepper_is_the_learned_systems_own_taylor_integrator() -> None:
    """The series computed in floating point during the fit and sympy's exact one give the
    same map (to rounding) on the cubic Nambu bracket."""
    _, stepper, report, starts = _learned("nambu_cubic")
    own = pr.taylor_integrator(report.system, report.kept.order)
    a = pr.integrate(stepper, starts, H, 20)
    b = pr.integrate(own, starts, H, 20)
    assert np.max(np.abs(a - b)) <= 1e-12


def test_affine_learned_stepper_keeps_the_casimir_to_round_off() -> None:
    system, stepper, _, starts = _learned("extended_pendulum")
    traj = pr.integrate(stepper, starts, H, LONG)
    c = system.casimirs(traj.reshape(-1, 3)).reshape(3, LONG + 1, -1)
    assert np.max(np.abs(c - c[:, :1])) <= 1e-12 * max(1.0, float(np.max(np.abs(c))))


def test_numeric_hj_series_matches_sympy() -> None:
    from poisson_rs.realizations.numeric_hj import hj_terms
    from poisson_rs.steppers.polynomial import realization_tables
    from poisson_rs.structures.polynomial import _lambdify, _term_table, hj_series

    system = _system("nambu_cubic")
    x = system.structure.x
    _, beta = realization_tables(system.structure, 3)
    _, coeffs, exps = _term_table([system.h], x)
    numeric = hj_terms(beta, (exps, coeffs), 3)
    exact = hj_series(system, 3, 3)
    pts = np.random.default_rng(0).normal(size=(8, 3))
    for (e, c), s in zip(numeric, exact, strict=True):
        got = (c * np.prod(pts[:, None, :] ** e[None], axis=2)).sum(1)
        want = _lambdify(x, [s])(*pts.T)[:, 0]
        assert np.allclose(got, want, rtol=1e-13, atol=1e-15)


def test_auto_mode_chooses_among_the_hamiltonian_degrees() -> None:
    system = _system("nambu_cubic")
    trajs = system.reference_solution(_starts(system, 5, 2), np.arange(21) * H)
    stepper, report = pr.learn(trajs, H, structure=system, max_degree=2)
    assert report.mode == "auto" and [c.family for c in report.candidates] == ["poly2"]
    assert report.explained and "NOT EXPLAINED" not in str(report)
    assert pr.integrate(stepper, trajs[0, 0], H, 3).shape == (4, 3)


def test_a_family_short_of_the_noise_level_is_reported_not_explained() -> None:
    """A linear H cannot make the cubic Nambu flow: the best fit is kept and the report says
    the data are not explained."""
    system = _system("nambu_cubic")
    trajs = system.reference_solution(_starts(system, 5, 2), np.arange(21) * H)
    _, report = pr.learn(trajs, H, structure=system, degree=1)
    assert report.kept.one_step > report.threshold
    assert not report.explained and "NOT EXPLAINED" in str(report)


# --- bad input: one clear error naming the input and the field --------------------------------


def _some(system: Any) -> np.ndarray:
    return system.reference_solution(_starts(system, 3, 0), np.arange(6) * H)


def test_wrong_dimension_is_refused() -> None:
    system = _system("nambu_cubic")
    bad = np.zeros((2, 6, 4))
    bad[..., 0] = np.arange(6)
    with pytest.raises(ValueError, match=r"trajectories\[0\]: records have dimension 4, but the "
                       r"structure .* has dimension 3"):  # fmt: skip
        pr.learn(bad, H, structure=system, mode="hamiltonian")


def test_states_outside_the_domain_are_refused() -> None:
    class HalfSpace(PolynomialPoissonSystem):
        """The cubic Nambu system restricted to x1 > 0."""

        def in_domain(self, x: np.ndarray) -> np.ndarray:
            return np.asarray(np.isfinite(x).all(-1) & (x[..., 0] > 0))

        def domain_text(self) -> str:
            return "x1 > 0"

    base = _system("nambu_cubic")
    system = HalfSpace(base.structure, str(base.h))
    trajs = _some(base)
    trajs[1, 2, 0] = -0.5
    with pytest.raises(ValueError, match=r"trajectories\[1\] must be x1 > 0 states: state 2"):
        pr.learn(trajs, H, structure=system, mode="hamiltonian")
    trajs[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"trajectories\[1\]: record 2, component 0 is nan"):
        pr.learn(trajs, H, structure=base, mode="hamiltonian")


@pytest.mark.parametrize("mode", ["map", "hj+data"])
def test_modes_that_do_not_apply_are_refused_naming_mode_and_structure(mode: str) -> None:
    system = _system("extended_pendulum")
    with pytest.raises(
        ValueError,
        match=rf"mode '{re.escape(mode)}' does not apply to the structure extended pendulum.*"
        "the modes that apply to it: 'auto', 'hamiltonian'",
    ):
        pr.learn(_some(system), H, structure=system, mode=mode)


def test_a_structure_without_a_hamiltonian_family_is_refused() -> None:
    from poisson_rs.protocols import PoissonSystemBase

    class Bare(PoissonSystemBase):
        title = "a bare structure"

    with pytest.raises(
        ValueError,
        match=r"mode 'hamiltonian' does not apply to the structure a bare structure; no mode of "
        "pr.learn applies to it",
    ):
        pr.learn(np.ones((2, 5, 2)), H, structure=Bare(), mode="hamiltonian")


def test_log_canonical_states_outside_the_orthant_are_refused() -> None:
    lv = pr.lotka_volterra([[0, 1], [-1, 0]], [1.0, 2.0])
    trajs = lv.reference_solution(np.array([[1.0, 0.8], [1.0, 1.2]]), np.arange(6) * H)
    trajs[0, 3, 1] = -0.1
    with pytest.raises(
        ValueError, match=r"trajectories\[0\] must be open positive orthant .* states: state 3"
    ):
        pr.learn(trajs, H, structure=lv, mode="hamiltonian")


def test_lotka_volterra_on_pnn_protocol_sits_on_its_integrators_floor() -> None:
    """PNN's protocol: u̇ = u(v − 2), v̇ = v(1 − u), h = 0.1, 100 steps from each of (1, 0.8),
    (1, 1), (1, 1.2); hidden states to T = 100. H = Σ a_i x_i − b_i ln x_i fitted through the
    log-canonical Taylor-HJ (K = 5) is within 1.2× of the true H through the same
    integrator."""
    lv = pr.lotka_volterra([[0, 1], [-1, 0]], [1.0, 2.0])
    trajs = lv.reference_solution(np.array([[1, 0.8], [1, 1.0], [1, 1.2]]), np.arange(101) * H)
    stepper, report = pr.learn(trajs, H, structure=lv)
    assert report.kept.family == "log+poly1" and report.kept.order == 5
    assert "ln(u)" in report.hamiltonian_text and "no Casimir" in report.gauge
    hidden = np.array([[1, 0.9], [1, 1.1], [0.8, 1.0]])
    ref = lv.reference_solution(hidden, np.arange(1001) * H)
    e_true = np.abs(pr.integrate(pr.taylor_integrator(lv, 5), hidden, H, 1000) - ref).max()
    e_learned = np.abs(pr.integrate(stepper, hidden, H, 1000) - ref).max()
    assert e_learned <= 1.2 * e_true, (e_learned, e_true)


def test_bad_structure_options_are_refused() -> None:
    system = _system("nambu_cubic")
    with pytest.raises(ValueError, match=r"structure: give the structure alone"):
        pr.learn(_some(system), H, structure=system, algebra="so3")
    with pytest.raises(ValueError, match=r"order = 7 is not available on the structure"):
        pr.learn(_some(system), H, structure=system, mode="hamiltonian", order=7)
    with pytest.raises(TypeError, match=r"structure must be a Poisson system"):
        pr.learn(_some(system), H, structure=object())
