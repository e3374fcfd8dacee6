"""Affine Poisson brackets (Lie–Poisson plus a constant 2-cocycle) integrated on their central
extension at level 1: the bracket and vector field against independent formulas, a non-cocycle
refused, the Casimirs of the extension kept, fitted orders against DOP853, scenes and the CLI."""

from __future__ import annotations

import csv
import pickle
from pathlib import Path

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.cli import main
from poisson_rs.scenes import load_scene

SCENE = Path(__file__).resolve().parents[1] / "scenes" / "extended_pendulum.toml"
STATES = np.array([[0.8, -0.5, 2.0], [0.0, 1.0, 0.5], [1.2, 0.3, 1.0]])


def e2_constants() -> np.ndarray:
    """e(2) with {u, r} = −2v, {v, r} = 2u in the package convention."""
    c = np.zeros((3, 3, 3))
    c[0, 2, 1], c[2, 0, 1] = 2.0, -2.0
    c[1, 2, 0], c[2, 1, 0] = -2.0, 2.0
    return c


def pendulum() -> pr.AffinePoissonSystem:
    h = {(2, 0, 0): 0.5, (0, 2, 0): 0.5, (0, 4, 0): -1.0 / 24.0}
    w = [[0, -1, 0], [1, 0, 0], [0, 0, 0]]
    return pr.affine_poisson_system(e2_constants(), w, h, component_names=("u", "v", "r"))


def test_bracket_and_vector_field_match_the_formulas() -> None:
    system = pendulum()
    rng = np.random.default_rng(3)
    x = rng.normal(size=(16, 3))
    u, v = x[:, 0], x[:, 1]
    pi = system.bivector(x)
    np.testing.assert_allclose(pi[:, 0, 1], -1.0)
    np.testing.assert_allclose(pi[:, 0, 2], -2.0 * v)
    np.testing.assert_allclose(pi[:, 1, 2], 2.0 * u)
    np.testing.assert_allclose(pi, -np.swapaxes(pi, 1, 2))
    # ẋ = π(x)∇H with ∇H by central differences, against the extension's field at level 1.
    eps = 1e-6
    grad = np.stack(
        [
            (system.hamiltonian(x + eps * e) - system.hamiltonian(x - eps * e)) / (2 * eps)
            for e in np.eye(3)
        ],
        axis=-1,
    )
    np.testing.assert_allclose(
        system.vector_field(x), np.einsum("nij,nj->ni", pi, grad), rtol=1e-7, atol=1e-8
    )


def test_casimir_is_r_minus_u2_minus_v2() -> None:
    system = pendulum()
    x = np.random.default_rng(5).normal(size=(12, 3))
    c = system.casimirs(x)
    assert c is not None and c.shape == (12, 1)
    oracle = x[:, 2] - x[:, 0] ** 2 - x[:, 1] ** 2
    # A Casimir up to scale and a constant: an affine function of the oracle.
    fit = np.polyfit(oracle, c[:, 0], 1)
    np.testing.assert_allclose(np.polyval(fit, oracle), c[:, 0], atol=1e-12)
    assert abs(fit[0]) > 1e-6
    assert system.casimir_degrees == (2,)


def test_a_non_cocycle_is_refused_naming_the_triple() -> None:
    # so(3) ⊕ R, ω_03 = 1: Jacobi fails on (1, 2, 3) since [e1, e2] = e0 and ω(e0, e3) ≠ 0.
    c = np.zeros((4, 4, 4))
    c[:3, :3, :3] = pr.LieAlgebra.so3().c
    w = np.zeros((4, 4))
    w[0, 3], w[3, 0] = 1.0, -1.0
    with pytest.raises(ValueError, match=r"not a 2-cocycle.*\(i, j, k\) = \(1, 2, 3\)"):
        pr.affine_poisson_system(c, w, {(2, 0, 0, 0): 1.0})
    with pytest.raises(ValueError, match="antisymmetric"):
        pr.affine_poisson_system(e2_constants(), np.ones((3, 3)), {(2, 0, 0): 1.0})
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        pr.affine_poisson_system(e2_constants(), np.zeros((2, 2)), {(2, 0, 0): 1.0})


@pytest.mark.parametrize(
    ("name", "order"),
    [("taylor1", 2.0), ("taylor3", 4.0), ("taylor5", 6.0), ("rk4", 4.0), ("midpoint", 2.0)],
)
def test_fitted_orders_against_dop853(name: str, order: float) -> None:
    system = pendulum()
    T = 2.0
    ref = pr.reference_solution(system, STATES, [T])[:, 0]
    if name.startswith("taylor"):
        stepper = pr.affine_taylor(system, int(name.removeprefix("taylor")))
    else:
        stepper = pr.affine_classical(system, name)
    hs, errs = [], []
    for n in (10, 20, 40):
        traj = pr.integrate(stepper, STATES, T / n, n)
        hs.append(T / n)
        errs.append(np.abs(traj[:, -1] - ref).max())
    slope = np.polyfit(np.log(hs), np.log(errs), 1)[0]
    assert slope == pytest.approx(order, abs=0.15)


def test_taylor_keeps_the_casimirs_of_the_extension() -> None:
    system = pendulum()
    stepper = pr.affine_taylor(system, 3)
    traj = pr.integrate(stepper, STATES, 0.1, 10_000, every=100)
    c = system.casimirs(traj)
    assert np.abs(c - c[:, :1]).max() < 1e-12
    # The level μ_z = 1 itself, on the extension.
    lifted = pr.integrate(stepper.inner, system.lift(STATES), 0.1, 10_000, every=100)
    assert np.abs(lifted[..., -1] - 1.0).max() < 1e-13
    rk4 = pr.integrate(pr.affine_classical(system, "rk4"), STATES, 0.1, 10_000, every=100)
    c = system.casimirs(rk4)
    assert np.abs(c - c[:, :1]).max() > 1e-8  # not a Poisson map: it drifts


def test_round_trip_and_pickle() -> None:
    system = pendulum()
    again = pr.AffinePoissonSystem.from_dict(system.to_dict())
    assert again == system and again.component_names == ("u", "v", "r")
    stepper = pickle.loads(pickle.dumps(pr.affine_taylor(system, 3)))
    np.testing.assert_array_equal(
        pr.integrate(stepper, STATES, 0.1, 20),
        pr.integrate(pr.affine_taylor(system, 3), STATES, 0.1, 20),
    )


def test_scene_matches_the_api_system() -> None:
    scene = load_scene(SCENE)
    assert scene.lie_system == pendulum()
    assert scene.lie_system.component_names == ("u", "v", "r")


def test_demo_and_stability_on_the_scene(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    assert main(["demo", "--scene", str(SCENE), "--out", str(out), "--steps", "50"]) == 0
    text = (out / "metrics.csv").read_text()
    for name in ("taylor3-exp", "taylor7-exp", "rk4", "midpoint"):
        assert name in text
    argv = ["stability", str(SCENE), "--quick", "--horizon", "2", "--no-progress"]
    assert main([*argv, "--out", str(tmp_path / "st")]) == 0


def test_chart_on_the_scene_fits_the_orders_and_keeps_the_casimir(tmp_path: Path) -> None:
    out = tmp_path / "chart"
    assert main(["chart", str(SCENE), "--quick", "--out", str(out)]) == 0
    with (out / "workprecision.csv").open(newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["failed"] == "False"]

    def slope(method: str) -> float:
        pts = sorted((float(r["h"]), float(r["error_T"])) for r in rows if r["method"] == method)
        return float(np.polyfit(np.log([p[0] for p in pts]), np.log([p[1] for p in pts]), 1)[0])

    assert slope("taylor3-exp") == pytest.approx(4.0, abs=0.3)
    assert slope("taylor5-exp") == pytest.approx(6.0, abs=0.3)
    assert slope("midpoint") == pytest.approx(2.0, abs=0.2)
    drift = {
        r["method"]: max(float(x["max_rel_dC"]) for x in rows if x["method"] == r["method"])
        for r in rows
    }
    # The Poisson maps keep r − u² − v² to round-off (the midpoint rule too: it is quadratic on
    # the extension); RK4 does not.
    for name in ("taylor3-exp", "taylor5-exp", "midpoint"):
        assert drift[name] < 1e-13, (name, drift[name])
    assert drift["rk4"] > 1e-9


def test_bad_cocycle_scene_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = SCENE.read_text().replace("cocycle = [[0, -1, 0]", "cocycle = [[0, -1, 1]")
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert main(["demo", "--scene", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "system.cocycle" in err and "antisymmetric" in err and "\n" not in err


def test_select_on_an_affine_system() -> None:
    system = pendulum()
    stepper, h, _ = pr.select(system, STATES[:1], T=2.0, target=1e-6, budget_s=5.0)
    n = round(2.0 / h)
    traj = pr.integrate(stepper, STATES[:1], h, n)
    ref = pr.reference_solution(system, STATES[:1], [2.0])[:, 0]
    assert np.linalg.norm(traj[:, -1] - ref) / np.linalg.norm(STATES[0]) <= 1e-6


def test_dask_rollout_is_bit_identical() -> None:
    da = pytest.importorskip("dask.array")
    stepper = pr.affine_taylor(pendulum(), 3)
    lazy = pr.integrate(stepper, da.from_array(STATES, chunks=2), 0.1, 50)
    np.testing.assert_array_equal(lazy.compute(), pr.integrate(stepper, STATES, 0.1, 50))


def _learned_extension_model(system: pr.AffinePoissonSystem) -> object:
    """A small S = Taylor-3 + t⁵·MLP trained briefly (seeded) on the extension's HJ residual."""
    from poisson_rs.integrators import BisectionIntegrator
    from poisson_rs.train import TrainConfig, export_bytes, train

    cfg = TrainConfig(
        system=system.extension,
        chart="exp",
        inputs="t,p",
        domain="cube",
        half_width=2.0,
        widths=(4, 4),
        taylor_order=3,
        iterations=40,
        h_max=0.1,
        seed=0,
    )
    result = train(cfg, progress=False)
    return BisectionIntegrator(export_bytes(result.model, cfg))


def test_learned_s_on_the_extension_keeps_the_casimir() -> None:
    """A learned S on the extension's exact groupoid is a Poisson map at level 1: the affine
    Casimir r − u² − v² stays at round-off whatever the network learned, and the states track
    the DOP853 reference like Taylor-3 does."""
    system = pendulum()
    learned = pr.affine_learned(system, _learned_extension_model(system))
    traj = pr.integrate(learned, STATES, 0.1, 500)
    c = traj[..., 2] - traj[..., 0] ** 2 - traj[..., 1] ** 2
    assert np.abs(c - c[:, :1]).max() < 1e-12
    ref = pr.reference_solution(system, STATES, 0.1 * np.arange(0, 501, 100))
    taylor = pr.integrate(pr.affine_taylor(system, 3), STATES, 0.1, 500, every=100)
    err = np.abs(traj[:, ::100] - ref).max()
    assert err < 10 * np.abs(taylor - ref).max() + 1e-12, err


def test_learned_s_of_another_system_is_refused() -> None:
    system = pendulum()
    with pytest.raises(ValueError, match="central extension"):
        pr.affine_learned(system, pr.load_model())
    with pytest.raises(TypeError, match="BisectionIntegrator"):
        pr.affine_learned(system, pr.affine_taylor(system, 3))


@pytest.mark.parametrize("size", [1e300, 1e16, np.inf])
def test_a_huge_cocycle_is_named(size: float) -> None:
    """ω = 1e300 overflowed in the extension's Taylor terms (OverflowError); |ω| is bounded by
    1e15, at which the terms stay finite through order 10."""
    w = [[0, -size, 0], [size, 0, 0], [0, 0, 0]]
    with pytest.raises(ValueError, match=r"^cocycle"):
        pr.affine_poisson_system(e2_constants(), w, {(2, 0, 0): 0.5})


def test_the_largest_cocycle_integrates() -> None:
    w = [[0, -1e15, 0], [1e15, 0, 0], [0, 0, 0]]
    system = pr.affine_poisson_system(e2_constants(), w, {(2, 0, 0): 0.5, (0, 2, 0): 0.5})
    traj = pr.integrate(pr.affine_taylor(system, 5), STATES, 1e-17, 3)
    assert np.isfinite(traj).all()
