"""pr.learn: a Poisson integrator from trajectories (H learned as a polynomial, or a map)."""

from __future__ import annotations

import argparse
import json
import math
import os
import pickle
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import poisson_rs as pr
from poisson_rs.learn import CasimirDriftWarning, learn, load_trajectories, prepare
from poisson_rs.learn.api import _map_base
from poisson_rs.learn.hamiltonian import _Model, fit_polynomial, relative_field_error
from poisson_rs.learn.map import build_map
from poisson_rs.learn.series import monomials, series_jacobian, taylor_series
from poisson_rs.learn.step import _chart_jacobians, _chart_jacobians_autograd, bisection_step
from poisson_rs.taylor import lie_taylor_coefficients

torch.set_num_threads(1)

BODY = pr.RigidBody((2.0, 1.0, 2.0 / 3.0))


def _sphere(rng: np.random.Generator, m: int) -> np.ndarray:
    x = rng.normal(size=(m, 3))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _trajectories(system: pr.LiePoissonSystem, y0: np.ndarray, h: float, records: int):
    return pr.reference_solution(system, y0, h * np.arange(records))


# --- the differentiable Taylor series -----------------------------------------------------------


@pytest.mark.parametrize(
    ("algebra", "degree", "order"),
    [(pr.LieAlgebra.so3(), 2, 7), (pr.LieAlgebra.sl2(), 3, 4), (pr.LieAlgebra.se3(), 2, 3)],
)
def test_series_matches_exact_rationals(algebra, degree, order) -> None:
    rng = np.random.default_rng(1)
    family = monomials(algebra.dim, degree, min_degree=1)
    theta = rng.normal(size=len(family))
    b, sk = taylor_series(algebra.c, family, torch.as_tensor(theta), order)
    exact = lie_taylor_coefficients(
        algebra.c, dict(zip(family, theta.tolist(), strict=True)), order
    )
    ref = np.zeros((order, b.size))
    for k, s_k in enumerate(exact):
        for e, c in s_k.items():
            ref[k, b.index[e]] = float(c)
    assert np.abs(sk.numpy() - ref).max() <= 1e-14 * np.abs(ref).max()


def test_complex_step_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(2)
    family = monomials(3, 3, min_degree=1)
    theta, d = rng.normal(size=(2, len(family)))
    _, _, jac = series_jacobian(BODY.algebra.c, family, theta, 5, 0.1)
    eps = 1e-6
    sp = series_jacobian(BODY.algebra.c, family, theta + eps * d, 5, 0.1)[1]
    sm = series_jacobian(BODY.algebra.c, family, theta - eps * d, 5, 0.1)[1]
    fd = (sp - sm) / (2 * eps)
    assert torch.allclose(jac @ torch.as_tensor(d), fd, rtol=0, atol=1e-8 * float(fd.abs().max()))


def test_series_jacobian_in_chunks_is_the_one_batch_jacobian(monkeypatch) -> None:
    """A memory budget below one batch splits the P + 1 complex steps into chunks of rows; the
    value and Jacobian are the one-batch ones (each row's series is independent)."""
    from poisson_rs.learn import series

    rng = np.random.default_rng(4)
    family = monomials(6, 3, min_degree=1)
    theta = rng.normal(size=len(family))
    c = pr.LieAlgebra.se3().c
    _, s_one, jac_one = series_jacobian(c, family, theta, 2, 0.1)
    row = series.series_row_bytes(6, family, 2)
    calls: list[int] = []
    original = series.taylor_series

    def counted(*args):
        calls.append(int(args[2].shape[0]))
        return original(*args)

    monkeypatch.setattr(series, "taylor_series", counted)
    monkeypatch.setattr(series, "SERIES_BATCH_BYTES", 10 * row)
    _, s_chunked, jac_chunked = series_jacobian(c, family, theta, 2, 0.1)
    assert max(calls) == 10 and sum(calls) == len(family) + 1
    assert torch.allclose(s_chunked, s_one, rtol=1e-14, atol=0)
    assert torch.allclose(jac_chunked, jac_one, rtol=1e-13, atol=1e-13 * float(jac_one.abs().max()))


@pytest.mark.parametrize(
    ("algebra", "degree", "order"),
    [(pr.LieAlgebra.so3(), 3, 5), (pr.LieAlgebra.se3(), 2, 5), (pr.LieAlgebra.se3(), 3, 2)],
)
def test_series_row_bound_covers_every_product_of_one_row(monkeypatch, algebra, degree, order):
    """The chunk size rests on series_row_bytes bounding what one row's largest truncated
    product holds: every product taylor_series forms (recorded through the basis' own pair
    tables) stays within it, per row, complex128."""
    from poisson_rs.learn import series

    family = monomials(algebra.dim, degree, min_degree=1)
    rows = 3
    theta = torch.as_tensor(np.random.default_rng(5).normal(size=(rows, len(family)))) + 0j
    largest = [0]
    real_mul = series.MonomialBasis.mul

    def recorded(self, a, b):
        ia, _, _, _, dense = self._mul_table(self.degree_of(a), self.degree_of(b))
        pairs = a.shape[-1] * b.shape[-1] if dense is not None else len(ia)
        lead = torch.broadcast_shapes(a.shape[:-1], b.shape[:-1])
        largest[0] = max(largest[0], 16 * math.prod(lead) * pairs // rows)
        return real_mul(self, a, b)

    monkeypatch.setattr(series.MonomialBasis, "mul", recorded)
    taylor_series(algebra.c, family, theta, order)
    assert 0 < largest[0] <= series.series_row_bytes(algebra.dim, family, order)


def test_ift_gradients_match_finite_differences_of_the_step_map() -> None:
    """dΦ^L/dθ (L = 1, 3) through the implicit steps, against central differences of the whole
    step map (Newton re-solved at θ ± εd)."""
    rng = np.random.default_rng(3)
    family = monomials(3, 2, min_degree=1)
    theta = np.array([BODY.polynomial.terms.get(e, 0.0) for e in family])
    theta = theta + 0.05 * rng.normal(size=theta.shape)
    starts = 1.5 * _sphere(rng, 6)
    targets = np.zeros((6, 3, 3))
    model = _Model(BODY.algebra, family, 5, 0.3)
    _, jac = model.residuals(theta, starts, targets, 3, True)
    d = rng.normal(size=theta.shape)
    eps = 1e-6
    rp, _ = model.residuals(theta + eps * d, starts, targets, 3, False)
    rm, _ = model.residuals(theta - eps * d, starts, targets, 3, False)
    fd = (rp - rm) / (2 * eps)
    assert np.abs(jac @ d - fd).max() <= 1e-7 * np.abs(fd).max()


@pytest.mark.parametrize("algebra", [pr.LieAlgebra.so3(), pr.LieAlgebra.se3()])
def test_closed_form_chart_jacobians_match_autograd(algebra) -> None:
    """sou, tar and their Jacobians in x and p (forward recursion beside the series) against
    row-by-row reverse-mode autograd of chart_maps, at seeded points."""
    rng = np.random.default_rng(30)
    n = algebra.dim
    c = torch.as_tensor(np.array(algebra.c, dtype=np.float64))
    x = torch.as_tensor(0.4 * rng.normal(size=(16, n)))
    p = torch.as_tensor(rng.normal(size=(16, n)))
    for got, ref in zip(_chart_jacobians(c, x, p), _chart_jacobians_autograd(c, x, p), strict=True):
        assert torch.allclose(got, ref, rtol=0, atol=1e-14 * float(ref.abs().max()))


def test_step_with_the_coefficient_jacobian_matches_the_full_one() -> None:
    """bisection_step's dμ'/dθ formed from ds/dθ (polynomial derivatives at p) equals
    dμ'/ds · ds/dθ, and the step's states and dμ'/dμ do not depend on which is asked for."""
    rng = np.random.default_rng(31)
    algebra = pr.LieAlgebra.se3()
    family = monomials(6, 2, min_degree=1)
    theta = 0.3 * rng.normal(size=len(family))
    b, s, ds = series_jacobian(algebra.c, family, theta, 3, 0.1)
    mu = torch.as_tensor(rng.normal(size=(12, 6)))
    full = bisection_step(b, algebra.c, s, mu, derivatives=True)
    chained = bisection_step(b, algebra.c, s, mu, derivatives=True, coeff_jacobian=ds)
    assert full.d_coeffs is not None and chained.d_coeffs is not None
    ref = full.d_coeffs @ ds
    assert torch.allclose(chained.d_coeffs, ref, rtol=0, atol=1e-13 * float(ref.abs().max()))
    assert torch.equal(full.out, chained.out) and torch.equal(full.d_state, chained.d_state)


# --- recovery of a known H -----------------------------------------------------------------------


def test_recovers_rigid_body_vector_field_and_keeps_casimirs() -> None:
    rng = np.random.default_rng(4)
    traj = _trajectories(BODY, _sphere(rng, 10), 0.1, 16)
    stepper, report = learn(traj, 0.1, algebra="so3", mode="hamiltonian", degree=2, seed=0)
    test = rng.normal(size=(200, 3))
    assert relative_field_error(report.system, BODY, test) <= 1e-6
    assert report.hamiltonian is not None and report.hamiltonian.degree == 2
    roll = pr.integrate(stepper, traj[:, 0], 0.1, 500)
    c = np.sum(roll**2, axis=-1)
    assert np.abs(c - c[:, :1]).max() <= 1e-13 * c.max()


def test_recovers_heavy_top_vector_field() -> None:
    top = pr.HeavyTop()
    rng = np.random.default_rng(5)
    y0 = np.concatenate([rng.normal(size=(6, 3)), _sphere(rng, 6)], axis=1)
    traj = _trajectories(top, y0, 0.05, 12)
    data = prepare(traj, 0.05, top.algebra, seed=0)
    fit = fit_polynomial(data, top.algebra, 2, order=5, max_iter=8)
    states = np.concatenate([rng.normal(size=(100, 3)), _sphere(rng, 100)], axis=1)
    assert relative_field_error(fit.system, top, states) <= 1e-6


def test_auto_prefers_the_smaller_family_when_it_fits() -> None:
    rng = np.random.default_rng(6)
    traj = _trajectories(BODY, _sphere(rng, 10), 0.1, 16)
    _, report = learn(traj, 0.1, algebra="so3", mode="auto")
    assert [c.family for c in report.candidates] == ["poly2"]
    assert report.kept.family == "poly2" and "smallest" in report.kept.reason
    # A cubic H: the quadratic family cannot reach the noise level, the cubic one is kept.
    cubic = pr.LiePoissonSystem(
        pr.LieAlgebra.so3(),
        pr.Polynomial({(2, 0, 0): 0.25, (0, 2, 0): 0.5, (0, 0, 2): 0.75, (1, 1, 1): 0.3}),
    )
    traj3 = _trajectories(cubic, _sphere(rng, 10), 0.1, 16)
    _, report3 = learn(traj3, 0.1, algebra="so3", mode="auto", max_iter=10)
    assert [c.family for c in report3.candidates] == ["poly2", "poly3"]
    assert report3.kept.family == "poly3"
    assert report3.candidates[1].one_step < 1e-3 * report3.candidates[0].one_step
    assert "poly2" in str(report3) and "KEPT" in str(report3)
    assert report3.explained and "NOT EXPLAINED" not in str(report3)
    # The quadratic family alone does not explain the cubic H's data, and the report says so.
    _, short = learn(traj3, 0.1, algebra="so3", mode="hamiltonian", degree=2, max_iter=10)
    assert short.kept.one_step > short.threshold
    assert not short.explained and "NOT EXPLAINED" in str(short)


# --- map mode ------------------------------------------------------------------------------------


def _random_map(seed: int) -> torch.nn.Module:
    s_fn = build_map(
        {(2, 0, 0): 0.25, (0, 2, 0): 0.5, (0, 0, 2): 0.75},
        pr.LieAlgebra.so3(),
        widths=(8, 8),
        h=0.1,
        seed=seed,
    )
    torch.manual_seed(seed)
    for lin in s_fn.linears:
        torch.nn.init.normal_(lin.weight, std=0.5)
        torch.nn.init.normal_(lin.bias, std=0.1)
    return s_fn


def _map_stepper(s_fn) -> pr.LearnedIntegrator:
    from poisson_rs.export import model_bytes

    raw = model_bytes(
        powers=s_fn.powers.numpy(),
        coeffs=s_fn.coeffs.detach().numpy(),
        layers=s_fn.exported_layers(),
        mlp_power=s_fn.mlp_power,
        chart="exp",
        system=_map_base(s_fn, pr.LieAlgebra.so3()),
        h_max=0.1,
        domain={"kind": "all"},
        record={"learn_mode": "map"},
    )
    return pr.LearnedIntegrator(raw)


def test_random_map_keeps_casimirs_and_rust_matches_torch(tmp_path) -> None:
    stepper = _map_stepper(_random_map(7))
    mu0 = _sphere(np.random.default_rng(7), 5)
    roll = pr.integrate(stepper, mu0, 0.1, 300)
    c = np.sum(roll**2, axis=-1)
    assert np.isfinite(roll).all()
    assert np.abs(c - 1.0).max() <= 1e-13
    one = pr.integrate(stepper, mu0, 0.1, 1)[:, -1]
    torch_one = stepper.torch_step(torch.as_tensor(mu0), 0.1).numpy()
    assert np.abs(one - torch_one).max() <= 1e-14
    # Round trips: the file and pickle step bit for bit like the original.
    path = tmp_path / "map.safetensors"
    path.write_bytes(stepper._bytes)
    again = pr.load_model(str(path))
    assert np.array_equal(pr.integrate(again, mu0, 0.1, 20), roll[:, :21])
    clone = pickle.loads(pickle.dumps(stepper))
    assert np.array_equal(pr.integrate(clone, mu0, 0.1, 20), roll[:, :21])


def test_map_mode_learns_and_records_provenance() -> None:
    rng = np.random.default_rng(8)
    traj = _trajectories(BODY, _sphere(rng, 10), 0.1, 6)
    stepper, report = learn(
        traj,
        0.1,
        algebra="so3",
        mode="map",
        seed=3,
        map_options={"kind": "network", "adam_steps": 10, "lbfgs_steps": 5, "widths": (8,)},
    )
    assert report.kept.family == "map" and report.hamiltonian is None
    assert report.kept.one_step < 1e-3
    meta = stepper.metadata
    assert meta["learn_mode"] == "map" and meta["data_sha256"] == report.data_sha256
    assert meta["seed"] == 3 and json.loads(meta["data_shape"]) == [10, 6, 3]
    c = np.sum(pr.integrate(stepper, traj[:, 0], 0.1, 100) ** 2, axis=-1)
    assert np.abs(c - c[:, :1]).max() <= 1e-13


def test_polynomial_map_learns_the_time_h_map_from_pairs(tmp_path) -> None:
    rng = np.random.default_rng(12)
    pairs = _trajectories(BODY, _sphere(rng, 120), 0.1, 2)
    stepper, report = learn(pairs, 0.1, algebra="so3", mode="map", seed=0)
    assert report.kept.family == "map-poly6" and report.hamiltonian is None
    assert report.kept.parameters <= 84
    # Oracle: the exact solution (Jacobi elliptic functions) at held-out states, t = 10.
    mu0 = _sphere(rng, 4)
    roll = pr.integrate(stepper, mu0, 0.1, 100)
    exact = pr.exact_solution(BODY, mu0, 0.1 * np.arange(101))
    assert np.abs(roll - exact).max() <= 1e-7
    assert np.abs(np.sum(roll**2, -1) - 1.0).max() <= 1e-13
    path = tmp_path / "map.safetensors"
    path.write_bytes(stepper._bytes)
    assert np.array_equal(pr.integrate(pr.load_model(str(path)), mu0, 0.1, 20), roll[:, :21])
    with pytest.raises(ValueError, match="map_options\\['kind'\\]"):
        learn(pairs, 0.1, algebra="so3", mode="map", map_options={"kind": "spline"})


# --- data: files and bad input -------------------------------------------------------------------


def test_loaders_agree(tmp_path) -> None:
    rng = np.random.default_rng(9)
    traj = _trajectories(BODY, _sphere(rng, 3), 0.1, 5)
    np.savez(tmp_path / "a.npz", trajectories=traj)
    rows = [[i, *r] for i, t in enumerate(traj) for r in t]
    np.savetxt(tmp_path / "a.csv", rows, delimiter=",", header="traj,m1,m2,m3", comments="")
    for name in ("a.npz", "a.csv"):
        got = load_trajectories(tmp_path / name)
        assert len(got) == 3 and all(
            np.allclose(g, t, rtol=0, atol=1e-15) for g, t in zip(got, traj, strict=True)
        )
    pytest.importorskip("zarr")
    pytest.importorskip("dask")
    from poisson_rs.ensembles import to_zarr

    rk4 = pr.classical(BODY, "rk4")
    to_zarr(rk4, traj[:, 0], 0.1, 4, tmp_path / "z")
    assert np.array_equal(
        np.stack(load_trajectories(tmp_path / "z")), pr.integrate(rk4, traj[:, 0], 0.1, 4)
    )


@pytest.mark.parametrize(
    ("data", "h", "match"),
    [
        (np.full((2, 4, 3), np.nan), 0.1, r"trajectories\[0\]: record 0, component 0 is nan"),
        (np.ones((2, 4, 4)), 0.1, "dimension 4, but the algebra"),
        (np.ones((2, 1, 3)), 0.1, "at least two records"),
        ([[[1.0, 2.0, 3.0], [1.0, 2.0]]], 0.1, "ragged"),
        (np.ones((2, 4, 3)), 0.0, "h must be finite and > 0"),
        (np.ones((2, 4, 3)), -1.0, "h must be finite and > 0"),
    ],
)
def test_bad_input_gets_one_clear_error(data, h, match) -> None:
    with pytest.raises(ValueError, match=match):
        learn(data, h, algebra="so3")


def test_drifting_casimirs_warn_with_their_size() -> None:
    rng = np.random.default_rng(10)
    traj = _trajectories(BODY, _sphere(rng, 4), 0.1, 12)
    traj = traj * (1 + 0.01 * np.arange(12))[None, :, None]  # |μ| grows: not Lie–Poisson
    with pytest.warns(CasimirDriftWarning, match=r"drift by up to 0\.1\d+ \(relative\)"):
        prepare(traj, 0.1, pr.LieAlgebra.so3())


def test_shooting_rollout_derivatives_match_finite_differences() -> None:
    family = monomials(3, 2, min_degree=1)
    theta = np.zeros(len(family))
    for e, c in {(2, 0, 0): 0.25, (0, 2, 0): 0.5, (0, 0, 2): 0.75, (1, 0, 0): 0.1}.items():
        theta[family.index(e)] = c
    model = _Model(pr.LieAlgebra.so3(), family, 5, 0.1)
    starts = _sphere(np.random.default_rng(13), 3)
    out, dth, dst = model.rollout(theta, starts, 6)
    assert np.abs(out.numpy()[:, 0] - starts).max() == 0.0
    d = np.random.default_rng(14).normal(size=len(theta))
    eps = 1e-6
    fd = (model.states(theta + eps * d, starts, 6) - model.states(theta - eps * d, starts, 6)) / (
        2 * eps
    )
    assert np.abs(dth.numpy() @ d - fd).max() <= 1e-7 * max(1.0, np.abs(fd).max())
    v = np.random.default_rng(15).normal(size=starts.shape)
    fd = (model.states(theta, starts + eps * v, 6) - model.states(theta, starts - eps * v, 6)) / (
        2 * eps
    )
    assert np.abs(np.einsum("bkij,bj->bki", dst.numpy(), v) - fd).max() <= 1e-7


def test_shooting_beats_one_step_residuals_on_a_noisy_trajectory() -> None:
    """One trajectory with noise of 1e-4: fitting every record from a free start (shooting)
    brings the learned vector field closer to the true one than one- and multi-step residuals."""
    y0 = np.array([np.cos(1.1), 0.0, np.sin(1.1)])
    traj = _trajectories(BODY, y0, 0.1, 121)
    for seed in range(3):
        noisy = traj + 1e-4 * np.random.default_rng(seed).normal(size=traj.shape)
        data = prepare(noisy, 0.1, pr.LieAlgebra.so3(), test_fraction=0.0)
        err = [
            relative_field_error(
                fit_polynomial(data, pr.LieAlgebra.so3(), 2, shooting=s, sparse=False).system,
                BODY,
                traj,
            )
            for s in (False, True)
        ]
        assert err[1] <= 0.5 * err[0]


# --- mode "hj+data": a known part of H plus what the data add ---------------------------------

_KNOWN = {(2, 0, 0): 0.25, (0, 2, 0): 0.5, (0, 0, 2): 0.75}


def _hj_data(records: int = 12):
    """Exact records of H = H_known + 0.05·μ₁μ₂μ₃, and the known part."""
    alg = pr.LieAlgebra.so3()
    known = pr.LiePoissonSystem(alg, pr.Polynomial(_KNOWN))
    truth = pr.LiePoissonSystem(alg, pr.Polynomial({**_KNOWN, (1, 1, 1): 0.05}))
    y0 = _sphere(np.random.default_rng(11), 5)
    return known, truth, y0, _trajectories(truth, y0, 0.1, records)


def test_hj_data_polynomial_correction_recovers_the_missing_term() -> None:
    known, truth, y0, trajs = _hj_data()
    stepper, report = learn(trajs, 0.1, system=known, mode="hj+data", degree=3, seed=0)
    assert report.kept.family == "known+poly3"
    # Oracle: the true vector field (gauge-free), and the exact Casimir |μ|².
    states = np.concatenate(trajs)
    assert relative_field_error(report.system, truth, states) <= 1e-6
    roll = pr.integrate(stepper, y0, 0.1, 300)
    assert np.abs(np.sum(roll**2, -1) - 1.0).max() <= 1e-13
    # Without the correction the known part alone is far off on the same data.
    assert relative_field_error(known, truth, states) >= 1e-2


def test_hj_data_network_blend_keeps_casimirs_and_the_data_term_pulls() -> None:
    known, _truth, y0, trajs = _hj_data(8)
    opts = {"widths": (8,), "adam_steps": 40, "lbfgs_steps": 10, "n_hj": 64}
    errors = {}
    for lam in (0.0, 10.0):
        stepper, report = learn(
            trajs,
            0.1,
            system=known,
            mode="hj+data",
            correction="network",
            lam=lam,
            map_options=opts,
            test_fraction=0.0,
        )
        assert report.kept.family == "known+network" and report.kept.parameters == 49
        errors[lam] = report.kept.one_step
        roll = pr.integrate(stepper, y0, 0.1, 200)
        assert np.isfinite(roll).all()
        assert np.abs(np.sum(roll**2, -1) - 1.0).max() <= 1e-13
    # The data term moves the map toward the data (loss_HJ alone keeps it at H_known's flow).
    assert errors[10.0] <= 0.75 * errors[0.0]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"algebra": "so3"}, "needs the known part of H: give system="),
        ({"correction": "spline"}, "correction must be one of"),
        ({"lam": -1.0}, "lam must be a finite number >= 0"),
        ({"lam": float("inf")}, "lam must be a finite number >= 0"),
    ],
)
def test_hj_data_bad_input_gets_one_clear_error(kwargs, match) -> None:
    known = pr.LiePoissonSystem(pr.LieAlgebra.so3(), pr.Polynomial(_KNOWN))
    kw = {"system": known, **kwargs}
    if "algebra" in kw:
        del kw["system"]
    with pytest.raises(ValueError, match=match):
        learn(np.ones((2, 4, 3)), 0.1, mode="hj+data", **kw)


# --- the command line ----------------------------------------------------------------------------


def test_cli_writes_a_model_with_its_provenance(tmp_path, capsys) -> None:
    from poisson_rs.learn import cli

    rng = np.random.default_rng(11)
    traj = _trajectories(BODY, _sphere(rng, 8), 0.1, 12)
    np.savez(tmp_path / "d.npz", trajectories=traj)
    parser = argparse.ArgumentParser()
    cli.add_parser(parser.add_subparsers())
    out = tmp_path / "m.safetensors"
    argv = ["learn", str(tmp_path / "d.npz"), "--algebra", "so3", "--h", "0.1", "--out"]
    args = parser.parse_args([*argv, str(out), "--seed", "2"])
    assert args.func(args) == 0
    model = pr.load_model(str(out))
    assert model.metadata["learn_mode"] == "auto" and model.metadata["seed"] == 2
    assert json.loads(model.metadata["data_shape"]) == [8, 12, 3]
    assert "KEPT" in capsys.readouterr().out
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert args.func(args) == 2  # exists, no --force
    bad = parser.parse_args(
        ["learn", str(tmp_path / "d.npz"), "--algebra", "so3", "--h", "-1", "--out", str(out)]
    )
    with pytest.raises(ValueError, match="--h"):
        bad.func(bad)


def test_cli_hj_data_reads_the_known_system(tmp_path) -> None:
    from poisson_rs.learn import cli

    known, truth, _, trajs = _hj_data(8)
    np.savez(tmp_path / "d.npz", trajectories=trajs)
    (tmp_path / "known.json").write_text(json.dumps(known.to_dict()))
    parser = argparse.ArgumentParser()
    cli.add_parser(parser.add_subparsers())
    out = tmp_path / "m.safetensors"
    argv = ["learn", str(tmp_path / "d.npz"), "--h", "0.1", "--out", str(out), "--mode"]
    argv += ["hj+data", "--degree", "3", "--system", str(tmp_path / "known.json")]
    args = parser.parse_args(argv)
    assert args.func(args) == 0
    model = pr.load_model(str(out))
    assert model.metadata["learn_mode"] == "hj+data"
    assert relative_field_error(model.system, truth, np.concatenate(trajs)) <= 1e-6
    (tmp_path / "bad.json").write_text("{")
    args = parser.parse_args([*argv[:-1], str(tmp_path / "bad.json"), "--force"])
    with pytest.raises(ValueError, match="--system"):
        args.func(args)


# --- Lotka–Volterra on a known log-canonical structure -------------------------------------------


def test_lotka_volterra_fit_recovers_h_and_rejects_states_off_the_orthant() -> None:
    from poisson_rs.learn.log_canonical import fit_lotka_volterra

    c = [[0.0, 1.0], [-1.0, 0.0]]
    lv = pr.lotka_volterra(c, [1.0, 2.0])
    reference = pr.log_canonical_classical(lv, "dop853", tol=1e-13)
    trajs = pr.integrate(reference, np.array([[1.0, 0.8], [1.0, 1.2]]), 0.1, 60)
    fit = fit_lotka_volterra(list(trajs), 0.1, c)
    # Oracle: the generating H = u − ln u + v − 2 ln v (c is invertible: no gauge).
    assert np.abs(fit.a - 1.0).max() <= 1e-6
    assert np.abs(fit.b - [1.0, 2.0]).max() <= 1e-6
    x0 = np.array([[1.0, 0.9]])
    learned = pr.integrate(fit.stepper, x0, 0.1, 100)
    truth = pr.integrate(pr.log_canonical_taylor(lv, 5), x0, 0.1, 100)
    assert np.abs(learned - truth).max() <= 1e-5
    with pytest.raises(ValueError, match=r"trajectories\[0\]: states must be finite and positive"):
        fit_lotka_volterra([-trajs[0]], 0.1, c)
    with pytest.raises(ValueError, match="h must be finite and > 0"):
        fit_lotka_volterra(list(trajs), 0.0, c)


# --- options, h and data checked before any fit --------------------------------------------------


def _never(*args, **kwargs):
    raise AssertionError("the fit ran")


@pytest.fixture
def no_fit(monkeypatch):
    """Every fit raises: a refusal in a test using this fixture came before the work."""
    from poisson_rs.learn import blend, hamiltonian
    from poisson_rs.learn import map as learn_map

    for module, name in (
        (hamiltonian, "fit_polynomial"),
        (learn_map, "fit_polynomial_map"),
        (learn_map, "fit_map"),
        (blend, "fit_blended_map"),
    ):
        monkeypatch.setattr(module, name, _never)


def _four() -> np.ndarray:
    return _trajectories(BODY, _sphere(np.random.default_rng(20), 4), 0.1, 6)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"order": -3}, r"order must be an integer in \[1, 12\], got -3"),
        ({"order": 2.5}, r"order must be an integer in \[1, 12\], got 2\.5"),
        ({"horizon": 2.5}, r"horizon must be an integer in \[1, 64\], got 2\.5"),
        ({"max_iter": 2.5}, r"max_iter must be an integer in \[1, 10000\], got 2\.5"),
        ({"mode": "map", "map_options": {"degree": 0}}, r"map_options\['degree'\] must be an"),
        ({"map_options": {"seed": 1}}, r"map_options\['seed'\] is not an option .*give seed="),
        ({"seed": -1}, r"seed must be an integer in \[0, 2\*\*63\), got -1"),
        ({"seed": 1.5}, r"seed must be an integer >= 0, got 1\.5"),
        ({"test_fraction": 0.9}, "test_fraction = 0.9 holds out 4 of 4 trajectories, leaving none"),
        ({"test_fraction": "x"}, "test_fraction must be a number in"),
        ({"max_degree": 5}, r"max_degree must be an integer in \[1, 4\], got 5"),
        ({"degree": 3, "max_degree": 2}, "degree = 3 exceeds max_degree = 2"),
        ({"progress": "yes"}, "progress must be True or False"),
    ],
)
def test_bad_options_get_one_clear_error_before_the_fit(no_fit, kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        learn(_four(), 0.1, algebra="so3", **kwargs)


@pytest.mark.parametrize("h", [1e-320, 5e-324, 1e300, 10**400])
def test_h_out_of_the_fits_range_is_refused_naming_h(no_fit, h) -> None:
    with pytest.raises(ValueError, match=r"h (= .* is outside|must be finite)"):
        learn(_four(), h, algebra="so3")


@pytest.mark.parametrize(
    ("scale", "match"),
    [
        (0.0, r"trajectories: every record is zero \(an equilibrium\)"),
        (1e-200, r"trajectories: the records' RMS \|μ\| is 1e-200, outside"),
        (1e200, r"trajectories: the records' RMS \|μ\| is 1e\+200, outside"),
    ],
)
def test_degenerate_data_are_refused_naming_the_data(no_fit, scale, match) -> None:
    traj = _four() * scale
    traj /= np.sqrt(np.mean(np.sum(_four() ** 2, -1)))  # RMS |μ| exactly `scale`
    with pytest.raises(ValueError, match=match):
        learn(traj, 0.1, algebra="so3")


def test_records_that_do_not_move_and_empty_data_are_refused(no_fit) -> None:
    still = np.tile(np.array([0.3, 0.4, 0.5]), (3, 6, 1))  # an equilibrium of every H... at rest
    with pytest.raises(ValueError, match="trajectories: the records do not move"):
        learn(still, 0.1, algebra="so3")
    with pytest.raises(
        ValueError, match=r"trajectories: got no trajectories \(shape \(0, 4, 3\)\)"
    ):
        learn(np.zeros((0, 4, 3)), 0.1, algebra="so3")


def test_a_tensor_that_requires_grad_is_data() -> None:
    traj = _four()
    tensor = torch.tensor(traj, requires_grad=True)
    alg = pr.LieAlgebra.so3()
    assert prepare(tensor, 0.1, alg).digest == prepare(traj, 0.1, alg).digest
    assert prepare(list(tensor), 0.1, alg).digest == prepare(traj, 0.1, alg).digest


def test_hj_data_bounds_the_known_h_degree_before_the_fit(no_fit) -> None:
    """Without degree=, the correction took the known H's degree unchecked (degree 8: the
    dense Taylor-HJ series past 2.5 GB); with it, the known terms still enter the series."""
    known = pr.LiePoissonSystem(
        pr.LieAlgebra.so3(), pr.Polynomial({(8, 0, 0): 1.0, (0, 2, 0): 0.5})
    )
    for kwargs in ({}, {"degree": 3}):
        with pytest.raises(ValueError, match="system: the known H has degree 8"):
            learn(_four(), 0.1, system=known, mode="hj+data", **kwargs)


# --- data that are not Lie–Poisson ---------------------------------------------------------------


def _damped_rigid_body(y0: np.ndarray, h: float, records: int, gamma: float) -> np.ndarray:
    """μ̇ = μ × I⁻¹μ − γμ (friction): |μ|² decays as e^(−2γt), not a Casimir any more."""
    from scipy.integrate import solve_ivp

    inertia = np.array([2.0, 1.0, 2.0 / 3.0])

    def rhs(_t, mu):
        return np.cross(mu, mu / inertia) - gamma * mu

    t = h * np.arange(records)
    return np.stack(
        [solve_ivp(rhs, (0, t[-1]), y, t_eval=t, rtol=1e-12, atol=1e-12).y.T for y in y0]
    )


def test_data_of_a_damped_rigid_body_are_refused_before_the_fit(no_fit) -> None:
    traj = _damped_rigid_body(_sphere(np.random.default_rng(21), 6), 0.1, 16, 0.05)
    with pytest.warns(CasimirDriftWarning):
        with pytest.raises(ValueError, match="do not come from a Lie–Poisson system"):
            learn(traj, 0.1, algebra="so3")


def test_a_trial_step_that_leaves_the_chart_is_rejected_not_raised(monkeypatch) -> None:
    """The exponential chart is singular for |ad_x| ≥ 2π: a Levenberg–Marquardt trial there
    (FloatingPointError from the step) is a rejected trial, and the fit ends where it was."""
    traj = _trajectories(BODY, _sphere(np.random.default_rng(22), 4), 0.1, 6)
    data = prepare(traj, 0.1, pr.LieAlgebra.so3(), test_fraction=0.0)
    original = _Model.residuals

    def residuals(self, theta, starts, targets, horizon, jacobian):
        if not jacobian:
            raise FloatingPointError("the exponential chart is singular here")
        return original(self, theta, starts, targets, horizon, jacobian)

    monkeypatch.setattr(_Model, "residuals", residuals)
    fit = fit_polynomial(data, pr.LieAlgebra.so3(), 2, max_iter=3, sparse=False, shooting=False)
    assert np.isfinite(fit.theta).all() and len(fit.history) == 1


def test_casimir_drift_is_compared_with_the_data_noise() -> None:
    """At σ = 1e-4 the noise alone moves |μ|² by ~1e-3: no warning. A drift 30× what the
    noise explains still warns."""
    y0 = np.array([np.cos(1.1), 0.0, np.sin(1.1)])
    traj = _trajectories(BODY, y0, 0.1, 121)
    noisy = traj + 1e-4 * np.random.default_rng(23).normal(size=traj.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CasimirDriftWarning)
        data = prepare(noisy, 0.1, pr.LieAlgebra.so3())
    assert data.casimir_drift > 1e-4  # the old fixed 1e-6 would have warned
    growing = noisy * (1 + 0.05 * np.linspace(0, 1, 121))[:, None]
    with pytest.warns(CasimirDriftWarning, match="the data's noise level .* explains up to"):
        prepare(growing, 0.1, pr.LieAlgebra.so3())


# --- what the report claims ----------------------------------------------------------------------


@pytest.mark.parametrize(("n_traj", "records"), [(2, 10), (1, 4)])
def test_with_nothing_held_out_the_report_says_training_error(n_traj, records) -> None:
    rng = np.random.default_rng(24)
    traj = _trajectories(BODY, _sphere(rng, n_traj), 0.1, records)
    _, report = learn(traj, 0.1, algebra="so3", mode="hamiltonian", degree=2, max_iter=5)
    text = str(report)
    assert "held-out" not in text and "nothing held out" in text
    assert not report.held_out
    assert "training one-step error" in report.kept.reason
    # What the checks cover: the records' span, and H only up to a Casimir.
    span = 0.1 * (records - 1)
    assert f"nothing beyond T = {span:g} was checked" in text
    assert "gauge-fixed" in text and "differ from the true H by a Casimir" in text


# --- map mode: one h only ------------------------------------------------------------------------


def test_a_learned_map_steps_at_its_data_h_only(tmp_path: Path) -> None:
    rng = np.random.default_rng(25)
    pairs = _trajectories(BODY, _sphere(rng, 40), 0.1, 2)
    stepper, report = learn(pairs, 0.1, algebra="so3", mode="map", map_options={"degree": 4})
    assert report.kept.family == "map-poly4"
    assert float(stepper.metadata["step_h"]) == 0.1  # what a loader of the file can enforce
    mu0 = _sphere(rng, 2)
    assert np.isfinite(pr.integrate(stepper, mu0, 0.1, 5)).all()
    for h in (0.05, 0.025, 0.1 * (1 - 1e-9)):
        with pytest.raises(ValueError, match=r"fitted for h = 0\.1 .* steps at that h only"):
            pr.integrate(stepper, mu0, h, 5)
    with pytest.raises(ValueError, match="steps at that h only"):
        stepper.torch_step(torch.as_tensor(mu0), 0.05)
    again = pickle.loads(pickle.dumps(stepper))
    with pytest.raises(ValueError, match="steps at that h only"):
        pr.integrate(again, mu0, 0.05, 5)
    # Its file, loaded back, keeps the rule (integrate reads the stepper's step_h).
    path = tmp_path / "map.safetensors"
    path.write_bytes(stepper._bytes)
    loaded = pr.load_model(path)
    assert loaded.step_h == 0.1
    with pytest.raises(ValueError, match="steps at that h only"):
        pr.integrate(loaded, mu0, 0.05, 5)
    assert np.isfinite(pr.integrate(loaded, mu0, 0.1, 5)).all()


# --- progress and the degrees tried --------------------------------------------------------------


def test_progress_bar_and_max_degree(capsys) -> None:
    cubic = pr.LiePoissonSystem(
        pr.LieAlgebra.so3(),
        pr.Polynomial({(2, 0, 0): 0.25, (0, 2, 0): 0.5, (0, 0, 2): 0.75, (1, 1, 1): 0.3}),
    )
    traj = _trajectories(cubic, _sphere(np.random.default_rng(26), 4), 0.1, 8)
    _, report = learn(
        traj, 0.1, algebra="so3", mode="hamiltonian", max_degree=2, max_iter=3, progress=True
    )
    # The quadratic family cannot reach the noise level of cubic data; it is the only one tried.
    assert [c.family for c in report.candidates] == ["poly2"]
    err = capsys.readouterr().err
    assert "learn" in err and "fit" in err
    learn(traj, 0.1, algebra="so3", mode="hamiltonian", degree=2, max_iter=3, progress=False)
    assert capsys.readouterr().err == ""


# --- the command line: refusals before the fit, and the output -----------------------------------


def _cli_args(*argv: str) -> argparse.Namespace:
    from poisson_rs.learn import cli

    parser = argparse.ArgumentParser()
    cli.add_parser(parser.add_subparsers())
    return parser.parse_args(["learn", *argv])


def test_cli_needs_the_algebra(tmp_path, monkeypatch) -> None:
    from poisson_rs.learn import api, cli

    monkeypatch.setattr(api, "learn", _never)
    np.savez(tmp_path / "d.npz", trajectories=_four())
    args = _cli_args(str(tmp_path / "d.npz"), "--h", "0.1", "--out", str(tmp_path / "m.st"))
    with pytest.raises(ValueError, match="--algebra: the Poisson structure is not assumed"):
        args.func(args)
    parser = argparse.ArgumentParser()
    sub = cli.add_parser(parser.add_subparsers())
    assert "required unless --system" in " ".join(sub.format_help().split())


def test_cli_probes_out_before_the_fit(tmp_path, monkeypatch) -> None:
    """/proc passes the checks on the name (a writable folder to root) but takes no new file:
    only writing there tells, and that is done before the fit."""
    from poisson_rs.learn import api

    if os.geteuid() != 0 or not os.path.isdir("/proc"):
        pytest.skip("needs root and /proc")
    monkeypatch.setattr(api, "learn", _never)
    np.savez(tmp_path / "d.npz", trajectories=_four())
    out = "/proc/learned-model.safetensors"
    args = _cli_args(str(tmp_path / "d.npz"), "--algebra", "so3", "--h", "0.1", "--out", out)
    with pytest.raises(ValueError, match=r"cannot write /proc/learned-model\.safetensors"):
        args.func(args)


def test_cli_does_not_replace_a_file_that_appears_during_the_fit(tmp_path, monkeypatch) -> None:
    from poisson_rs.learn import api

    out = tmp_path / "m.safetensors"
    real_learn = api.learn

    def learn_then_someone_writes(*args, **kwargs):
        result = real_learn(*args, **{**kwargs, "max_iter": 2})
        out.write_bytes(b"another run's model")
        return result

    monkeypatch.setattr(api, "learn", learn_then_someone_writes)
    np.savez(tmp_path / "d.npz", trajectories=_four())
    argv = [str(tmp_path / "d.npz"), "--algebra", "so3", "--h", "0.1", "--out", str(out)]
    argv += ["--mode", "hamiltonian", "--degree", "2", "--no-progress"]
    args = _cli_args(*argv)
    assert args.func(args) == 2
    assert out.read_bytes() == b"another run's model"
    out.unlink()
    args = _cli_args(*argv, "--force")
    assert args.func(args) == 0
    assert pr.load_model(str(out)).metadata["learn_mode"] == "hamiltonian"
