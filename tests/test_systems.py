"""Tests for Lie algebras, polynomial Hamiltonians, Lie–Poisson systems and their reference flow."""

from __future__ import annotations

import json
import pickle
from typing import Any

import numpy as np
import pytest
import torch
from conftest import count_dop853_rhs

from poisson_rs import reference
from poisson_rs.reference import reference_solution
from poisson_rs.structures.lie_poisson import (
    HeavyTop,
    LieAlgebra,
    LiePoissonSystem,
    Polynomial,
    RigidBody,
)
from poisson_rs.structures.lie_poisson_reference import exact_solution

torch.set_num_threads(1)

SL2_H = Polynomial({(2, 0, 0): 0.5, (0, 1, 1): 1.0, (0, 2, 0): 0.3, (1, 1, 0): 0.2, (3, 0, 0): 0.1})


def _bracket(c: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """[x, y] = Σ x_i y_j c[i,j,k] e_k."""
    return np.einsum("ijk,i,j->k", c, x, y)


# --- LieAlgebra ----------------------------------------------------------------------------------


@pytest.mark.parametrize("make", [LieAlgebra.so3, LieAlgebra.se3, LieAlgebra.sl2])
def test_named_algebras_are_valid_and_ad_is_the_bracket(make: Any) -> None:
    alg = make()
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(2, alg.dim))
    np.testing.assert_allclose(alg.ad(x) @ y, _bracket(alg.c, x, y), atol=1e-14)
    np.testing.assert_allclose(alg.ad_transpose(x), np.swapaxes(alg.ad(x), -1, -2))
    batch = rng.normal(size=(4, 5, alg.dim))
    assert alg.ad(batch).shape == (4, 5, alg.dim, alg.dim)
    torch_ad = alg.ad(torch.tensor(batch))
    np.testing.assert_array_equal(torch_ad.numpy(), alg.ad(batch))
    assert alg.c.dtype == np.float64 and not alg.c.flags.writeable
    assert alg.is_so3() == (alg.name == "so3")
    assert make() == alg and hash(make()) == hash(alg)


def test_named_brackets() -> None:
    se3, sl2 = LieAlgebra.se3(), LieAlgebra.sl2()
    e = np.eye(6)
    # [R1, T2] = T3, [T1, T2] = 0, [R1, R2] = R3
    np.testing.assert_array_equal(_bracket(se3.c, e[0], e[4]), e[5])
    np.testing.assert_array_equal(_bracket(se3.c, e[3], e[4]), np.zeros(6))
    np.testing.assert_array_equal(_bracket(se3.c, e[0], e[1]), e[2])
    h, ee, f = np.eye(3)
    np.testing.assert_array_equal(_bracket(sl2.c, h, ee), 2 * ee)
    np.testing.assert_array_equal(_bracket(sl2.c, h, f), -2 * f)
    np.testing.assert_array_equal(_bracket(sl2.c, ee, f), h)


def test_algebra_equality_ignores_the_name_and_round_trips() -> None:
    named, plain = LieAlgebra.se3(), LieAlgebra(LieAlgebra.se3().c)
    assert named == plain and hash(named) == hash(plain) and plain.name is None
    assert LieAlgebra.so3() != LieAlgebra.sl2()
    assert LieAlgebra(-np.asarray(LieAlgebra.so3().c)) != LieAlgebra.so3()
    assert not LieAlgebra(-np.asarray(LieAlgebra.so3().c)).is_so3()
    for alg in (named, LieAlgebra.sl2()):
        back = LieAlgebra.from_dict(json.loads(json.dumps(alg.to_dict())))
        assert back == alg and back.name == alg.name
        assert pickle.loads(pickle.dumps(alg)) == alg
    assert "se3" in repr(named)
    with pytest.raises(AttributeError, match="immutable"):
        named.foo = 1  # type: ignore[attr-defined]


def _random_antisymmetric(seed: int, n: int = 3) -> np.ndarray:
    c = np.random.default_rng(seed).normal(size=(n, n, n))
    return c - c.transpose(1, 0, 2)


@pytest.mark.parametrize(
    ("c", "match"),
    [
        (np.ones((3, 3, 3)), "not antisymmetric"),
        (_random_antisymmetric(1), "Jacobi identity"),
        (np.zeros((3, 3)), r"shape \(n, n, n\)"),
        (np.zeros((2, 3, 3)), r"shape \(n, n, n\)"),
        (np.zeros(()), r"shape \(n, n, n\)"),
        (np.zeros((0, 0, 0)), "between 1 and 10"),
        (np.zeros((11, 11, 11)), "between 1 and 10"),
        (np.full((3, 3, 3), np.nan), "finite"),
        (np.where(np.eye(3)[:, :, None] > 0, np.inf, 0.0) * np.ones((3, 3, 3)), "finite"),
        (np.zeros((3, 3, 3), dtype=bool), "booleans"),
        (np.zeros((3, 3, 3), dtype=complex), "complex"),
        ([[["a"]]], "real numbers"),
        ([[[0.0, 1.0], [0.0]], [[0.0], [0.0]]], "real numbers"),
    ],
)
def test_bad_structure_constants(c: Any, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        LieAlgebra(c)


def test_structure_constant_tolerance_is_relative() -> None:
    c = 1e6 * np.asarray(LieAlgebra.so3().c)
    LieAlgebra(c + 1e-8 * np.random.default_rng(0).normal(size=c.shape) * (c != 0))
    with pytest.raises(ValueError, match="not antisymmetric"):
        bad = np.array(LieAlgebra.so3().c)
        bad[0, 1, 2] += 1e-9
        LieAlgebra(bad)


# --- Polynomial ----------------------------------------------------------------------------------


def test_polynomial_values_gradient_and_storage() -> None:
    poly = Polynomial({(0, 2, 0): 0.25, (2, 0, 0): 1 / 3, (0, 0, 2): 0.2, (1, 1, 1): 0.0})
    assert poly.dim == 3 and poly.degree == 2 and poly.is_homogeneous(2)
    assert not poly.is_homogeneous(3)
    assert list(poly.terms) == [(0, 0, 2), (0, 2, 0), (2, 0, 0)]  # sorted, zero term dropped
    with pytest.raises(TypeError):
        poly.terms[(1, 0, 0)] = 1.0  # type: ignore[index]
    mu = np.random.default_rng(0).normal(size=(4, 5, 3))
    expected = mu[..., 0] ** 2 / 3 + mu[..., 1] ** 2 / 4 + mu[..., 2] ** 2 / 5
    np.testing.assert_allclose(poly(mu), expected, rtol=1e-15)
    np.testing.assert_allclose(poly.gradient(mu), mu * [2 / 3, 0.5, 0.4], rtol=1e-15)
    assert poly == Polynomial.quadratic_diagonal([2 / 3, 0.5, 0.4])
    powers, coeffs = poly.to_arrays()
    assert powers.dtype == np.int64 and powers.shape == (3, 3) and coeffs.dtype == np.float64
    assert Polynomial.from_arrays(powers, coeffs) == poly
    assert hash(Polynomial(dict(poly.terms))) == hash(poly)


def test_polynomial_torch_matches_numpy_and_autograd_matches_gradient() -> None:
    rng = np.random.default_rng(7)
    terms = {tuple(int(e) for e in rng.integers(0, 4, 4)): float(rng.normal()) for _ in range(12)}
    terms[(0, 0, 0, 0)] = 0.5
    poly = Polynomial(terms)
    mu = rng.normal(size=(6, 4))
    mu[0] = 0.0  # exponent-0 and exponent-1 factors at 0: no NaN in the backward pass
    mu_t = torch.tensor(mu, requires_grad=True)
    value = poly(mu_t)
    np.testing.assert_allclose(value.detach().numpy(), poly(mu), rtol=1e-14, atol=1e-14)
    (grad,) = torch.autograd.grad(value.sum(), mu_t)
    np.testing.assert_allclose(grad.numpy(), poly.gradient(mu), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(poly.gradient(mu_t).detach().numpy(), poly.gradient(mu), rtol=1e-14)
    # Direct evaluation as an independent check.
    direct = sum(a * np.prod(mu ** np.array(e), axis=-1) for e, a in poly.terms.items())
    np.testing.assert_allclose(poly(mu), direct, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize(
    ("coefficients", "match"),
    [
        ({}, "at least one term"),
        ([((2, 0), 1.0)], "mapping"),
        ({(2, 0): 1.0, (1, 0, 0): 1.0}, "same length"),
        ({(2, -1): 1.0}, "non-negative ints"),
        ({(2.0, 0): 1.0}, "non-negative ints"),
        ({(True, 0): 1.0}, "non-negative ints"),
        ({"20": 1.0}, "tuples of ints"),
        ({(): 1.0}, "at least one entry"),
        ({(2, 0): float("nan")}, "finite"),
        ({(2, 0): float("inf")}, "finite"),
        ({(2, 0): "1"}, "real number"),
        ({(2, 0): True}, "real number"),
        ({(2, 0): 1j}, "real number"),
        ({(13, 0): 1.0}, "degree 13 > 12"),
        ({(7, 6): 0.0}, "degree 13 > 12"),
    ],
)
def test_bad_polynomials(coefficients: Any, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        Polynomial(coefficients)


def test_polynomial_round_trip_and_edge_cases() -> None:
    poly = Polynomial({(1, 0, 3): -2.5, (0, 0, 0): 1.0, (0, 1, 0): 1e-300})
    back = Polynomial.from_dict(json.loads(json.dumps(poly.to_dict())))
    assert back == poly and dict(back.terms) == dict(poly.terms)
    assert pickle.loads(pickle.dumps(poly)) == poly
    zero = Polynomial({(0, 0): 0.0})
    assert zero.dim == 2 and zero.degree == 0 and not zero.terms
    np.testing.assert_array_equal(zero(np.ones((4, 2))), np.zeros(4))
    np.testing.assert_array_equal(zero.gradient(np.ones((4, 2))), np.zeros((4, 2)))
    assert Polynomial.from_dict(json.loads(json.dumps(zero.to_dict()))) == zero
    with pytest.raises(ValueError, match="mu must have shape"):
        poly(np.ones(2))
    with pytest.raises(ValueError, match="'dim' and 'terms'"):
        Polynomial.from_dict({"terms": []})
    with pytest.raises(ValueError, match="rows"):
        Polynomial.from_dict({"dim": 3, "terms": [[1, 0, 1.0]]})


# --- Lie–Poisson systems -------------------------------------------------------------------------


def test_generic_so3_system_reproduces_rigid_body() -> None:
    inertia = (1.5, 2.0, 2.5)
    body = RigidBody(inertia)
    generic = LiePoissonSystem(
        LieAlgebra.so3(), Polynomial.quadratic_diagonal([1 / v for v in inertia]), name="free"
    )
    mu = np.random.default_rng(1).normal(size=(7, 3)) * 3
    np.testing.assert_allclose(generic.hamiltonian(mu), body.hamiltonian(mu), rtol=1e-15)
    np.testing.assert_allclose(generic.grad_hamiltonian(mu), body.grad_hamiltonian(mu), rtol=1e-15)
    np.testing.assert_allclose(generic.vector_field(mu), body.vector_field(mu), atol=1e-14)
    np.testing.assert_allclose(generic.casimirs(mu)[..., 0], body.casimir(mu), rtol=1e-15)
    # The same data, but a different kind of object: not equal (RigidBody has the exact flow).
    assert generic != body and body.algebra == generic.algebra
    assert body.polynomial == generic.polynomial and body.dim == 3


def test_rigid_body_is_a_system_and_keeps_its_api() -> None:
    body = RigidBody((1, 2, 3))
    assert isinstance(body, LiePoissonSystem) and body.inertia == (1.0, 2.0, 3.0)
    assert repr(body) == "RigidBody(inertia=(1.0, 2.0, 3.0))"
    assert {body: 1}[RigidBody((1.0, 2.0, 3.0))] == 1
    assert pickle.loads(pickle.dumps(body)) == body
    mu_t = torch.tensor([[1.0, 2.0, 4.0]], dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(body.hamiltonian(mu_t).sum(), mu_t)
    np.testing.assert_allclose(grad.numpy(), body.grad_hamiltonian(mu_t.detach().numpy()))
    np.testing.assert_allclose(
        body.vector_field(mu_t).detach().numpy(), body.vector_field(mu_t.detach().numpy())
    )


@pytest.mark.parametrize("inertia", [(True, 2, 3), (1.0, np.True_, 3.0)])
def test_rigid_body_rejects_booleans(inertia: Any) -> None:
    with pytest.raises(ValueError, match="not booleans"):
        RigidBody(inertia)


def test_heavy_top_vector_field_is_the_closed_form() -> None:
    top = HeavyTop((1.0, 1.5, 2.0), 0.981, (0.2, -0.3, 1.0))
    mu = np.random.default_rng(2).normal(size=(9, 6))
    m, g = mu[:, :3], mu[:, 3:]
    omega, chi = m / np.array(top.inertia), np.array(top.com)
    expected = np.concatenate(
        [np.cross(m, omega) + top.mgl * np.cross(g, chi), np.cross(g, omega)], axis=-1
    )
    np.testing.assert_allclose(top.vector_field(mu), expected, atol=1e-14)
    h = 0.5 * np.sum(m * omega, axis=-1) + top.mgl * g @ chi
    np.testing.assert_allclose(top.hamiltonian(mu), h, rtol=1e-14)
    np.testing.assert_allclose(top.casimirs(mu), np.stack([(g * g).sum(-1), (m * g).sum(-1)], -1))
    torch_field = top.vector_field(torch.tensor(mu)).numpy()
    np.testing.assert_allclose(torch_field, expected, atol=1e-14)
    assert HeavyTop().inertia == (1.0, 1.5, 2.0) and HeavyTop().mgl == 0.981


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"inertia": (1.0, 0.0, 1.0)}, "strictly positive"),
        ({"inertia": (1.0, 1.0)}, "exactly 3"),
        ({"mgl": -1.0}, "non-negative"),
        ({"mgl": float("nan")}, "mgl must be finite"),
        ({"mgl": True}, "mgl must be a real number"),
        ({"mgl": "1"}, "mgl must be a real number"),
        ({"com": (0.0, float("inf"), 1.0)}, "com entries must be finite"),
        ({"com": (0.0, 1.0)}, "exactly 3"),
        ({"com": (0.0, False, 1.0)}, "not booleans"),
    ],
)
def test_heavy_top_rejects_bad_parameters(kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        HeavyTop(**kwargs)


def test_system_construction_errors_and_state_validation() -> None:
    with pytest.raises(ValueError, match="3 variables but the algebra has dimension 6"):
        LiePoissonSystem(LieAlgebra.se3(), Polynomial.quadratic_diagonal([1.0, 1.0, 1.0]))
    with pytest.raises(TypeError, match="algebra must be a LieAlgebra"):
        LiePoissonSystem(np.zeros((3, 3, 3)), SL2_H)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="hamiltonian must be a Polynomial"):
        LiePoissonSystem(LieAlgebra.sl2(), {(2, 0, 0): 1.0})  # type: ignore[arg-type]
    system = LiePoissonSystem(LieAlgebra.sl2(), SL2_H)
    with pytest.raises(ValueError, match=r"mu must have shape \(\.\.\., 3\)"):
        system.vector_field(np.ones((2, 6)))
    with pytest.raises(ValueError, match="real numbers"):
        system.hamiltonian(["a", "b", "c"])
    with pytest.raises(ValueError, match="complex"):
        system.hamiltonian(np.ones(3, dtype=complex))
    with pytest.raises(ValueError, match=r"mu must have shape"):
        system.hamiltonian(torch.ones(2))
    with pytest.raises(AttributeError, match="immutable"):
        system.name = "x"  # type: ignore[misc]
    unknown = LiePoissonSystem(LieAlgebra(np.zeros((2, 2, 2))), Polynomial({(1, 1): 1.0}))
    assert unknown.casimirs(np.ones(2)) is None


def test_vector_field_keeps_casimirs_and_energy_infinitesimally() -> None:
    rng = np.random.default_rng(3)
    systems = [HeavyTop(com=(0.3, -0.2, 1.0)), LiePoissonSystem(LieAlgebra.sl2(), SL2_H)]
    for system in systems:
        mu = torch.tensor(rng.normal(size=(8, system.dim)), requires_grad=True)
        field = system.vector_field(mu).detach()
        (grad_h,) = torch.autograd.grad(system.hamiltonian(mu).sum(), mu)
        np.testing.assert_allclose((grad_h * field).sum(-1).numpy(), 0.0, atol=1e-13)
        casimirs = system.casimirs(mu)
        for k in range(casimirs.shape[-1]):
            (grad_c,) = torch.autograd.grad(casimirs[..., k].sum(), mu, retain_graph=True)
            np.testing.assert_allclose((grad_c * field).sum(-1).numpy(), 0.0, atol=1e-13)
            # Casimirs are in the kernel of the Poisson tensor: {C, ·} = 0.
            pi = torch.as_tensor(system.poisson_tensor(mu.detach().numpy()))
            np.testing.assert_allclose((grad_c[..., None, :] @ pi).numpy(), 0.0, atol=1e-13)


@pytest.mark.parametrize(
    "system",
    [
        RigidBody((1, 2, 3)),
        HeavyTop((1.0, 1.5, 2.0), 0.5, (0.1, 0.2, 1.0)),
        LiePoissonSystem(LieAlgebra.sl2(), SL2_H, name="sl2 test"),
        LiePoissonSystem(LieAlgebra.se3(), Polynomial({(1, 0, 0, 0, 0, 1): 2.0})),
    ],
)
def test_systems_round_trip_through_json(system: LiePoissonSystem) -> None:
    data = json.loads(json.dumps(system.to_dict()))
    assert data["kind"] == system.kind
    back = LiePoissonSystem.from_dict(data)
    assert type(back) is type(system) and back == system and hash(back) == hash(system)
    assert back.name == system.name
    assert type(system).from_dict(data) == system
    assert pickle.loads(pickle.dumps(system)) == system


def test_system_from_dict_errors() -> None:
    with pytest.raises(ValueError, match="'kind'"):
        LiePoissonSystem.from_dict({"inertia": [1, 2, 3]})
    with pytest.raises(ValueError, match="unknown system kind"):
        LiePoissonSystem.from_dict({"kind": "pendulum"})
    with pytest.raises(ValueError, match="needs a 'mgl' entry"):
        LiePoissonSystem.from_dict({"kind": "heavy_top", "inertia": [1, 2, 3], "com": [0, 0, 1]})
    with pytest.raises(ValueError, match="expected a 'rigid_body' dictionary"):
        RigidBody.from_dict(HeavyTop().to_dict())


# --- reference_solution --------------------------------------------------------------------------


def test_reference_solution_matches_the_exact_rigid_body_flow() -> None:
    body = RigidBody((1.5, 2.0, 2.5))
    mu0 = np.array([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]])
    times = np.array([0.0, 0.5, 3.0, 10.0])
    exact = exact_solution(body, mu0, times)
    np.testing.assert_allclose(reference_solution(body, mu0, times), exact, atol=1e-10)
    generic = LiePoissonSystem(body.algebra, body.polynomial)
    np.testing.assert_allclose(reference_solution(generic, mu0, times), exact, atol=1e-10)


@pytest.mark.parametrize(
    "system",
    [HeavyTop(com=(0.3, -0.2, 1.0)), LiePoissonSystem(LieAlgebra.sl2(), SL2_H)],
    ids=["heavy_top", "sl2"],
)
def test_reference_solution_keeps_casimirs_and_energy(system: LiePoissonSystem) -> None:
    rng = np.random.default_rng(4)
    mu0 = 0.5 * rng.normal(size=(3, system.dim))
    times = np.linspace(0.0, 5.0, 11)
    traj = reference_solution(system, mu0, times)
    assert traj.shape == (3, 11, system.dim)
    np.testing.assert_array_equal(traj[:, 0], mu0)
    casimirs = system.casimirs(traj)
    np.testing.assert_allclose(casimirs - casimirs[:, :1], 0.0, atol=1e-10)
    energy = system.hamiltonian(traj)
    np.testing.assert_allclose(energy - energy[:, :1], 0.0, atol=1e-10)


def test_reference_solution_shapes_and_bad_input() -> None:
    top = HeavyTop()
    assert reference_solution(top, np.ones(6), [0.0, 0.1]).shape == (2, 6)
    assert reference_solution(top, np.ones((2, 6)), [0.1]).shape == (2, 1, 6)
    assert reference_solution(top, np.ones((0, 6)), [0.1]).shape == (0, 1, 6)
    assert reference_solution(top, np.ones(6), []).shape == (0, 6)
    # Backward in time undoes forward.
    fwd = reference_solution(top, np.ones(6), [1.0])[0]
    np.testing.assert_allclose(reference_solution(top, fwd, [-1.0])[0], np.ones(6), atol=1e-11)
    with pytest.raises(TypeError, match="system must be a Poisson system"):
        reference_solution("top", np.ones(6), [1.0])  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"mu0 must have shape \(6,\) or \(n, 6\)"):
        reference_solution(top, np.ones(3), [1.0])
    with pytest.raises(ValueError, match="mu0 must be finite"):
        reference_solution(top, np.full(6, np.nan), [1.0])
    with pytest.raises(ValueError, match="times must be finite"):
        reference_solution(top, np.ones(6), [np.inf])
    with pytest.raises(ValueError, match="times must be a 1-D array"):
        reference_solution(top, np.ones(6), 1.0)
    with pytest.raises(ValueError, match="rtol must be finite and > 0"):
        reference_solution(top, np.ones(6), [1.0], rtol=0.0)


def test_reference_solution_work_is_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    top = HeavyTop()
    runs = count_dop853_rhs(monkeypatch)
    with pytest.raises(RuntimeError, match="non-finite"):
        reference_solution(top, np.full(6, 1e200), [1.0])
    assert runs == []  # refused before any integration
    monkeypatch.setattr(reference, "_DOP853_MAX_STEPS", 500, raising=False)
    with pytest.raises(RuntimeError, match="budget"):
        reference_solution(top, np.full(6, 1e8), [10.0])
    # Within the budget: 12 right-hand sides a step, and the one that stops it.
    assert max(runs, default=0) <= 12 * 500 + 1, runs
