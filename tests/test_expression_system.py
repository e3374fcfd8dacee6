"""Any structure with an expression Hamiltonian (pr.with_hamiltonian / ExpressionSystem): the
core's field against each family's own on polynomial H, Taylor-HJ by jets against the symbolic
series on polynomial H, fitted orders and kept Casimirs on the non-polynomial scenes, pickling,
and bad input."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.expressions import ExpressionError
from poisson_rs.scenes import load_scene
from poisson_rs.structures import system_from_dict
from poisson_rs.untrusted import InputError

SCENES = Path(__file__).resolve().parent.parent / "scenes"


def _scene(name: str) -> pr.Scene:
    return load_scene(SCENES / f"{name}.toml")


def _rigid_body() -> pr.RigidBody:
    return pr.RigidBody((1.5, 2.0, 2.5))


def _pendulum() -> object:
    return load_scene(SCENES / "extended_pendulum.toml").system


def _nambu() -> object:
    return load_scene(SCENES / "nambu_cubic.toml").system


def _lotka_volterra() -> object:
    return load_scene(SCENES / "lotka_volterra_3d.toml").system


# The family's own polynomial (or log-polynomial) H, written as an expression.
SAME_H = {
    "rigid body": (_rigid_body, "x1**2/3 + x2**2/4 + x3**2/5"),
    "affine": (_pendulum, "u**2/2 + v**2/2 - v**4/24"),
    "nambu": (_nambu, "x1**2/2 + x2**2/3 + x3**2/4"),
}


@pytest.mark.parametrize("case", list(SAME_H))
def test_field_equals_the_familys_own_on_its_polynomial_h(case: str) -> None:
    make, text = SAME_H[case]
    base = make()
    s = pr.with_hamiltonian(base, text)
    x = np.random.default_rng(5).uniform(-1.0, 1.0, size=(12, s.dim))
    np.testing.assert_allclose(s.hamiltonian(x), base.hamiltonian(x), rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(s.vector_field(x), base.vector_field(x), rtol=1e-13, atol=1e-14)


def test_log_canonical_field_with_an_expression() -> None:
    base = _lotka_volterra()
    x = np.random.default_rng(6).uniform(0.5, 1.5, size=(8, 3))
    s = pr.with_hamiltonian(base, "x1 + x2 + x3 - log(x1) - 2*log(x2) - 0.5*log(x3)")
    grad = np.stack([1 - 1 / x[:, 0], 1 - 2 / x[:, 1], 1 - 0.5 / x[:, 2]], axis=1)
    expected = np.einsum("nij,nj->ni", base.bivector(x), grad)
    np.testing.assert_allclose(s.vector_field(x), expected, rtol=1e-13, atol=1e-14)
    with pytest.raises(ValueError, match="positive"):
        s.check_states([[1.0, -1.0, 1.0]])
    with pytest.raises(ValueError, match="no realization for Taylor-HJ by jets"):
        s.taylor_integrator(3)
    assert s.taylor_charts() == ()


@pytest.mark.parametrize("order", [1, 3, 5])
def test_jets_equal_the_symbolic_series_on_the_rigid_body(order: int) -> None:
    body = _rigid_body()
    s = pr.with_hamiltonian(body, SAME_H["rigid body"][1])
    x0 = np.array([[0.3, -0.2, 0.5], [1.0, 0.5, -0.4]])
    jets = pr.integrate(s.taylor_integrator(order), x0, 0.1, 60)
    symbolic = pr.integrate(pr.taylor_integrator(body, order, chart="exp"), x0, 0.1, 60)
    np.testing.assert_allclose(jets, symbolic, rtol=0, atol=1e-14)


def test_jets_equal_the_symbolic_series_on_affine_and_polynomial_brackets() -> None:
    for make, text, order in ((_pendulum, SAME_H["affine"][1], 3), (_nambu, SAME_H["nambu"][1], 3)):
        base = make()
        s = pr.with_hamiltonian(base, text)
        x0 = np.asarray(base.demo_states)[:1] * 0.5
        jets = pr.integrate(s.taylor_integrator(order), x0, 0.1, 30)
        symbolic = pr.integrate(pr.taylor_integrator(base, order), x0, 0.1, 30)
        np.testing.assert_allclose(jets, symbolic, rtol=0, atol=1e-13)


# (scene, order): its initial state 0 to T = 1, errors against DOP853 at h = 0.2, 0.1, 0.05.
ORDERS = [
    ("extended_pendulum_pnn", 1),
    ("extended_pendulum_pnn", 3),
    ("extended_pendulum_pnn", 5),
    ("rigid_body_potential", 1),
    ("rigid_body_potential", 3),
    ("rigid_body_potential", 5),
    ("point_vortices", 1),
    ("point_vortices", 3),
    ("point_vortices_4", 1),
]


@pytest.mark.parametrize(("name", "order"), ORDERS)
def test_jet_taylor_fits_order_m_plus_one(name: str, order: int) -> None:
    scene = _scene(name)
    s = scene.system
    x0 = np.asarray(scene.points)[:1]
    hs = np.array([0.2, 0.1, 0.05])
    ref = s.reference_solution(x0, np.array([0.0, 1.0]))[:, -1]
    errs = [
        np.abs(pr.integrate(s.taylor_integrator(order), x0, h, round(1 / h))[:, -1] - ref).max()
        for h in hs
    ]
    slope = np.polyfit(np.log(hs), np.log(errs), 1)[0]
    assert abs(slope - (order + 1)) < 0.35, (errs, slope)


def test_an_h_longer_than_the_live_registers_fits_each_methods_order() -> None:
    """The vortices' H plus a cubic of 56 distinct terms: a program of over 256 instructions
    (the core evaluates its derivatives on reused register slots). The implicit midpoint rule
    (its Newton Jacobians from those derivatives) fits order 2, jets m = 1 order 2, RK4 order 4,
    against the reference solution."""
    from itertools import combinations_with_replacement

    from poisson_rs.expressions import MAX_LIVE, live_values

    vortices = _scene("point_vortices")
    cubic = " + ".join(
        f"{1e-3 * (1 + k / 50):.6f}*x{i + 1}*x{j + 1}*x{m + 1}"
        for k, (i, j, m) in enumerate(combinations_with_replacement(range(6), 3))
    )
    s = pr.with_hamiltonian(vortices.system.base, f"{vortices.system.h.text} + {cubic}")
    assert len(s.h.program) > MAX_LIVE and live_values(s.h.program) < 32
    x0 = np.asarray(vortices.points)[:1]
    ref = s.reference_solution(x0, np.array([0.0, 1.0]))[:, -1]
    hs = np.array([0.2, 0.1, 0.05])
    for stepper, order in ((s.classical("midpoint"), 2), (s.taylor_integrator(1), 2),
                           (s.classical("rk4"), 4)):  # fmt: skip
        errs = [np.abs(pr.integrate(stepper, x0, h, round(1 / h))[:, -1] - ref).max() for h in hs]
        slope = np.polyfit(np.log(hs), np.log(errs), 1)[0]
        assert abs(slope - order) < 0.35, (stepper, errs, slope)


def test_an_h_whose_field_exceeds_the_program_runs_on_its_tape() -> None:
    """A 10-D H of 150 cubic terms beside a quadratic (781 instructions): π∇H written out would
    exceed the core's 1024-instruction field program, so the system keeps none and the core
    differentiates H's tape in lanes. Its field equals autograd's π∇H on the canonical bracket,
    RK4 fits order 4 against the reference, and the torch step refuses in one line."""
    from itertools import combinations_with_replacement, islice

    torch = pytest.importorskip("torch")
    base = pr.PolynomialPoissonSystem(
        pr.PolynomialBivector(10, {(i, i + 5): "1" for i in range(5)}), "x1**2"
    )
    cubic = " + ".join(
        f"{0.01 * (1 + k / 50):.5f}*x{i + 1}*x{j + 1}*x{m + 1}"
        for k, (i, j, m) in enumerate(islice(combinations_with_replacement(range(10), 3), 150))
    )
    quadratic = " + ".join(f"x{i}**2" for i in range(1, 11))
    s = pr.with_hamiltonian(base, f"0.5*({quadratic}) + {cubic}")
    assert s.field_program is None and len(s.h.program) > 512
    x = np.random.default_rng(8).uniform(-0.5, 0.5, size=(9, 10))
    xt = torch.tensor(x, requires_grad=True)
    (g,) = torch.autograd.grad(s.h.evaluate(xt, torch).sum(), xt)
    g = g.numpy()
    np.testing.assert_allclose(s.vector_field(x), np.hstack([g[:, 5:], -g[:, :5]]), rtol=1e-13,
                               atol=1e-13)  # fmt: skip
    x0 = x[:2] * 0.5
    ref = s.reference_solution(x0, np.array([0.0, 1.0]))[:, -1]
    hs = np.array([0.2, 0.1, 0.05])
    rk4 = s.classical("rk4")
    errs = [np.abs(pr.integrate(rk4, x0, h, round(1 / h))[:, -1] - ref).max() for h in hs]
    assert abs(np.polyfit(np.log(hs), np.log(errs), 1)[0] - 4) < 0.35, errs
    with pytest.raises(ValueError, match=r"^hamiltonian: .*longer than the core's field program"):
        rk4.torch_step(torch.tensor(x0), 0.1)


@pytest.mark.parametrize("name", ["extended_pendulum_pnn", "rigid_body_potential"])
def test_jets_keep_the_casimirs_to_round_off_where_rk4_does_not(name: str) -> None:
    scene = _scene(name)
    s = scene.system
    x0 = np.asarray(scene.points)
    c0 = s.casimirs(x0)
    drift = {}
    for label, stepper in (("jets", s.taylor_integrator(1)), ("rk4", s.classical("rk4"))):
        traj = pr.integrate(stepper, x0, 0.1, 10_000, every=100)
        c = s.casimirs(traj.reshape(-1, s.dim)).reshape(len(x0), -1, c0.shape[-1])
        drift[label] = np.abs(c - c0[:, None]).max() / np.abs(c0).max()
    assert drift["jets"] <= 1e-13, drift
    assert drift["rk4"] > 1e3 * drift["jets"], drift


@pytest.mark.parametrize(
    ("name", "gamma"), [("point_vortices", [1.0, 1.0, 0.5]), ("point_vortices_4", [1, 1, 0.5, 0.5])]
)
def test_vortex_impulses_are_kept_and_the_bracket_has_no_casimir(
    name: str, gamma: list[float]
) -> None:
    scene = _scene(name)
    s = scene.system
    assert s.casimirs(np.asarray(scene.points)) is None
    g = np.asarray(gamma)
    traj = pr.integrate(s.taylor_integrator(1), np.asarray(scene.points), 0.05, 4000, every=40)
    xs, ys = traj[..., 0::2], traj[..., 1::2]
    impulses = np.stack(
        [(g * xs).sum(-1), (g * ys).sum(-1), (g * (xs**2 + ys**2)).sum(-1)], axis=-1
    )
    assert np.abs(impulses - impulses[:, :1]).max() < 1e-12


def test_pickled_systems_and_steppers_step_bit_identically() -> None:
    s = _scene("extended_pendulum_pnn").system
    x0 = np.asarray(s.demo_states) * 0.3
    for stepper in (s.taylor_integrator(3), s.classical("rk4"), s.classical("midpoint")):
        back = pickle.loads(pickle.dumps(stepper))
        np.testing.assert_array_equal(
            pr.integrate(stepper, x0, 0.1, 20), pr.integrate(back, x0, 0.1, 20)
        )
    assert pickle.loads(pickle.dumps(s)) == s
    assert system_from_dict(s.to_dict()) == s


@pytest.mark.parametrize("scene", ["extended_pendulum_pnn", "point_vortices"])
def test_rk4_in_wide_blocks_is_each_trajectory_alone_bit_for_bit(scene: str) -> None:
    """RK4 on an expression field runs 32 trajectories a block (a block of 8 or fewer stays
    narrow, a lone one takes one lane): 75 states (chunks of 64 and 11: two full wide blocks,
    one partly filled) and 72 (64 and 8: a narrow block) must give each trajectory's own
    one-state bits. A trajectory that fails (its field overflows) leaves its block's other
    lanes alone."""
    s = _scene(scene).system
    rng = np.random.default_rng(7)
    base = np.asarray(s.demo_states, dtype=float)
    x0 = base[rng.integers(len(base), size=75)] * (1 + 0.05 * rng.normal(size=(75, s.dim)))
    x0[40] = 1e200  # its field overflows: the trajectory fails on its first step
    rk4 = s.classical("rk4")
    alone = np.stack([pr.integrate(rk4, x, 0.05, 30, every=3, on_failure="ignore") for x in x0])
    for n in (75, 72):
        together = pr.integrate(rk4, x0[:n], 0.05, 30, every=3, on_failure="ignore")
        np.testing.assert_array_equal(together, alone[:n])
    assert np.isnan(alone[40, -1]).all() and np.isfinite(np.delete(alone, 40, 0)).all()


def test_a_step_outside_the_domain_of_h_fails_the_trajectory_not_the_process() -> None:
    s = _scene("point_vortices").system
    # Vortices 1 and 2 on top of each other: log(0) in H.
    x0 = np.array([[0.5, 0.0, 0.5, 0.0, -0.3, -0.8], [1.0, 0.0, -0.5, 0.6, -0.3, -0.8]])
    with pytest.warns(RuntimeWarning, match="1 of 2 trajectories failed"):
        traj, info = pr.integrate(s.taylor_integrator(3), x0, 0.05, 5, return_info=True)
    assert not info.converged[0] and info.converged[1]
    assert info.failure_code[0] == 3
    assert np.isnan(traj[0, -1]).all() and np.isfinite(traj[1]).all()


def test_bad_input_is_refused_naming_the_field() -> None:
    with pytest.raises(ExpressionError, match="hamiltonian: unknown name 'w'"):
        pr.with_hamiltonian(_rigid_body(), "w**2")
    # A structure that neither gives its bracket as polynomials nor builds expression systems
    # of its own kind (the charged particle does: tests/test_charged_particle.py).
    from poisson_rs.protocols import PoissonSystemBase

    opaque = type("Opaque", (pr.RigidBody,), {"bracket_terms": PoissonSystemBase.bracket_terms})
    with pytest.raises(ValueError, match=r"structure: .*does not give its bracket"):
        pr.with_hamiltonian(opaque((1.5, 2.0, 2.5)), "x3**2/2")
    s = pr.with_hamiltonian(_rigid_body(), "cos(x1)")
    for order in (0, 9, True):
        with pytest.raises(ValueError, match="order"):
            s.taylor_integrator(order)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown method 'rk5'"):
        s.classical("rk5")
    with pytest.raises(ValueError, match="chart 'cayley'"):
        s.taylor_integrator(3, "cayley")


def test_scene_errors_name_the_key(tmp_path: Path) -> None:
    text = (SCENES / "rigid_body_potential.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("cos(x3)", "cos(x3"))
    with pytest.raises(InputError, match="hamiltonian: missing"):
        load_scene(bad)
    bad.write_text(text.replace('[system.structure]\nkind = "rigid_body"', "[system.other]"))
    with pytest.raises(InputError, match=r"system\.structure"):
        load_scene(bad)
