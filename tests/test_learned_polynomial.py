"""Learned generating functions on the order-n realization of a polynomial bivector: the HJ
residual (fitted order of the exact Taylor terms), the Rust step and derivatives against torch,
the model file through load_model and integrate, training, and bad input."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
import torch

import poisson_rs as pr
from poisson_rs.export import safetensors_bytes
from poisson_rs.integrators import LearnedPolynomialIntegrator
from poisson_rs.realizations import polynomial_hj as hj
from poisson_rs.structures.polynomial import (
    PolynomialBivector,
    PolynomialPoissonSystem,
    RealizationTaylorIntegrator,
)
from poisson_rs.train import train
from poisson_rs.untrusted import InputError

#: The cubic Nambu scene (scenes/nambu_cubic.toml).
NAMBU = PolynomialPoissonSystem(
    PolynomialBivector.nambu("x1**2/2 + x2**2/2 + x3**2/2 + x1**3/3"),
    "x1**2/2 + x2**2/3 + x3**2/4",
)
STATES = np.array([[0.3, 0.5, -0.4], [0.1, -0.6, 0.3]])


def _config(**kw: object) -> hj.PolynomialTrainConfig:
    base: dict[str, object] = {
        "system": NAMBU,
        "taylor_order": 3,
        "realization_order": 3,
        "widths": (8, 6),
    }
    base.update(kw)
    return hj.PolynomialTrainConfig(**base)  # type: ignore[arg-type]


def _random_network(cfg: hj.PolynomialTrainConfig, seed: int) -> hj.PolynomialRealizationGenerating:
    """The configuration's model with every layer drawn at random and no output scaling: a
    network that really contributes to S."""
    s_fn = hj.build_model(cfg)
    s_fn.output_scale = 1.0
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for layer in s_fn.linears:
            layer.weight.copy_(
                0.8 * torch.randn(layer.weight.shape, generator=gen, dtype=torch.float64)
            )
            layer.bias.copy_(
                0.3 * torch.randn(layer.bias.shape, generator=gen, dtype=torch.float64)
            )
    return s_fn


def _states(n: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=gen, dtype=torch.float64) * 1.4 - 0.7


@pytest.mark.parametrize(("order", "expected"), [(1, 2), (2, 2), (3, 4)])
def test_taylor_terms_leave_a_residual_of_the_fitted_order(order, expected):
    # r = O(t^m), or O(t^{m+1}) where S_{m+1} vanishes: S_2 = 0 (π∇H·∇H = 0) and, on the
    # symmetric realization of order 3, S_4 = 0 too.
    cfg = _config(taylor_order=order, widths=())
    s_fn = hj.build_model(cfg)
    assert s_fn.tables.next_term_vanishes == (expected == order + 1)
    x = _states(3, 0)
    times = 0.05 * 0.5 ** np.arange(4)
    r = np.array(
        [
            hj.hj_residual(s_fn, torch.full((3,), t, dtype=torch.float64), x).abs().numpy()
            for t in times
        ]
    )
    slopes = [np.polyfit(np.log(times), np.log(r[:, j]), 1)[0] for j in range(3)]
    assert np.allclose(slopes, expected, atol=0.1), slopes


def test_term_polynomials_match_sympy_and_have_exact_gradients_at_zero():
    tables = hj.realization_tables(NAMBU, 3, 3)
    beta = hj.TermPolynomials(tables.beta, 3)
    v = torch.zeros(2, 6, dtype=torch.float64, requires_grad=True)
    out = beta(v)
    (g,) = torch.autograd.grad(out[:, 0].sum(), v)
    # β(x, 0) = x, and ∂β¹/∂x¹ = 1 at the origin (no NaN from 0^0).
    assert torch.equal(out.detach(), torch.zeros(2, 3, dtype=torch.float64))
    assert torch.isfinite(g).all() and g[0, 3] == 1.0
    x = _states(5, 1)
    p = 0.1 * _states(5, 2)
    b_sym, _, _ = NAMBU.structure.realization(3)
    import sympy

    syms = (*sympy.symbols("p1:4", real=True), *NAMBU.structure.x)
    f = sympy.lambdify(syms, b_sym, "numpy")
    want = np.stack(f(*torch.cat([p, x], 1).numpy().T), -1)
    assert np.allclose(beta(torch.cat([p, x], 1)).numpy(), want, rtol=0, atol=1e-15)


@pytest.mark.parametrize("n", [3, 5])
def test_rust_step_and_derivatives_equal_torch(n):
    s_fn = _random_network(_config(realization_order=n), seed=3)
    core = hj.core_model(s_fn)
    x = _states(64, 4)
    want = hj.step_map(s_fn, x, 0.1).numpy()
    got, info = core.rollout(x.numpy(), 0.1, 1)
    assert info["converged"].all() and np.isfinite(want).all()
    assert np.abs(got[:, 1] - want).max() <= 1e-11
    t = torch.full((64,), 0.07, dtype=torch.float64)
    xv = x.clone().requires_grad_(True)
    s = s_fn(t, xv)
    (g,) = torch.autograd.grad(s.sum(), xv, create_graph=True)
    hess = torch.stack(
        [torch.autograd.grad(g[:, i].sum(), xv, retain_graph=True)[0] for i in range(3)], 1
    )
    rs, rg, rh = core.derivatives(0.07, x.numpy())
    assert np.abs(rs - s.detach().numpy()).max() <= 1e-13
    assert np.abs(rg - g.detach().numpy()).max() <= 1e-13
    assert np.abs(rh - hess.numpy()).max() <= 1e-12


def test_untrained_model_steps_as_taylor_hj():
    # The last layer starts at zero: the learned integrator is exactly Taylor-HJ at the start.
    s_fn = hj.build_model(_config())
    got, _ = hj.core_model(s_fn).rollout(STATES, 0.1, 20)
    want, _ = RealizationTaylorIntegrator(NAMBU, 3, 3).rollout(STATES, 0.1, 20, 1)
    assert np.array_equal(got, want)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[hj.PolynomialTrainResult, object]:
    cfg = _config(widths=(8,), iterations=40, batch=256, seed=0)
    result = train(cfg, progress=False)
    path = tmp_path_factory.mktemp("models") / "nambu.safetensors"
    hj.save_result(result, path, name="nambu-test", command="pytest")
    return result, path


def test_training_lowers_the_residual_below_the_taylor_terms(trained):
    result, _ = trained
    assert result.iterations_run == 40
    assert np.isfinite(result.losses).all()
    assert result.validation_rms < result.baseline_rms


def test_model_file_loads_and_integrates_like_torch(trained):
    result, path = trained
    stepper = pr.load_model(path)
    assert isinstance(stepper, LearnedPolynomialIntegrator)
    assert (stepper.taylor_order, stepper.realization_order) == (3, 3)
    assert stepper.system.to_dict() == NAMBU.to_dict()
    out = pr.integrate(stepper, STATES, h=0.1, n_steps=3)
    x = torch.as_tensor(STATES)
    for _ in range(3):
        x = hj.step_map(result.model, x, 0.1)
    assert np.abs(out[:, -1] - x.numpy()).max() <= 1e-11
    again = pickle.loads(pickle.dumps(stepper))
    assert np.array_equal(pr.integrate(again, STATES, h=0.1, n_steps=3), out)
    with pytest.raises(ValueError, match="h_max"):
        pr.integrate(stepper, STATES, h=0.2, n_steps=1)


def test_casimir_drift_is_that_of_the_realization(trained):
    # The realization of order 3 is Poisson to O(|p|^3): the network cannot help the Casimir,
    # whose drift per step is O(h^5) (odd n) whatever S is; measured ~1e-12 a step at h = 0.1.
    _, path = trained
    out = pr.integrate(pr.load_model(path), STATES, h=0.1, n_steps=100)
    c = NAMBU.casimirs(out)[..., 0]
    drift = np.abs(c - c[:, :1]).max()
    assert 1e-14 < drift < 1e-9


def _file_with(path, *, meta=None, drop=(), tensors=None) -> bytes:
    stepper = pr.load_model(path)
    data = stepper._bytes
    size = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + size])
    raw = dict(header.pop("__metadata__"))
    base = 8 + size
    arrays = {}
    for name, e in header.items():
        dtype = {"F64": "<f8", "I64": "<i8"}[e["dtype"]]
        a, b = e["data_offsets"]
        arrays[name] = np.frombuffer(data[base + a : base + b], dtype=dtype).reshape(e["shape"])
    raw.update(meta or {})
    arrays.update(tensors or {})
    for k in drop:
        raw.pop(k, None)
        arrays.pop(k, None)
    return safetensors_bytes(arrays, raw)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"meta": {"structure": "nambu"}}, "unknown model structure 'nambu'"),
        ({"meta": {"realization_order": "9"}}, "realization_order"),
        ({"meta": {"taylor_order": "x"}}, "taylor_order"),
        ({"meta": {"system": "{}"}}, "system"),
        (
            {
                "meta": {
                    "system": json.dumps(
                        {**NAMBU.to_dict(), "hamiltonian": "__import__('os').getcwd()"}
                    )
                }
            },
            "may hold only numbers",
        ),
        ({"meta": {"h_max": "-1"}}, "h_max"),
        ({"drop": ("tar.index",)}, "tar.index"),
        ({"tensors": {"sou.exponents": -np.ones((1, 6), np.int64)}}, "sou"),
        ({"tensors": {"taylor.exponents": np.zeros((10, 3), np.int64)}}, "taylor.exponents"),
    ],
)
def test_bad_model_files_get_one_clear_error(trained, tmp_path, change, match):
    _, path = trained
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(_file_with(path, **change))
    with pytest.raises(ValueError, match=match):
        pr.load_model(bad)


_OTHER_H = {**NAMBU.to_dict(), "hamiltonian": "x1**2/2 + x2**2/3 + x3**2/5"}
#: The so(3) bracket: the cubic Nambu bracket without its x1**2 term (Jacobi holds).
_OTHER_BIVECTOR = {
    k: v for k, v in NAMBU.to_dict().items() if k not in ("entries", "casimir", "kind")
} | {"kind": "polynomial_bivector", "entries": [[0, 1, "x3"], [0, 2, "-x2"], [1, 2, "x1"]]}


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"meta": {"system": json.dumps(_OTHER_H)}}, "system"),
        ({"meta": {"system": json.dumps(_OTHER_BIVECTOR)}}, "system"),
        ({"meta": {"realization_order": "4"}}, "realization_order"),
        ({"meta": {"taylor_order": "2"}}, "taylor_order"),
        ({"meta": {"widths": "[9]"}}, "widths"),
        ({"drop": ("mlp_power",)}, "mlp_power"),
    ],
    ids=["hamiltonian", "bivector", "realization_order", "taylor_order", "widths", "mlp_power"],
)
def test_metadata_that_disagrees_with_the_tensors_is_refused(trained, tmp_path, change, field):
    # The core steps the tables and the network; the studies score ``system``: a file whose
    # metadata was edited would step one S and report another system or order.
    _, path = trained
    bad = tmp_path / "edited.safetensors"
    bad.write_bytes(_file_with(path, **change))
    with pytest.raises(InputError) as err:
        pr.load_model(bad)
    assert err.value.field == field
    assert str(bad) in err.value.source


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("taylor_order", 0),
        ("taylor_order", 6),
        ("realization_order", 0),
        ("realization_order", 7),
        ("widths", (0,)),
        ("h_max", -0.1),
        ("x_min", (0.0, 0.0)),
        ("x_max", (-1.0, -1.0, -1.0)),
        ("schedule", "linear"),
        ("batch", True),
        ("system", {"kind": "lie_poisson"}),
    ],
)
def test_bad_config_fields_are_named(field, value):
    cfg = _config(**{field: value})
    with pytest.raises(ValueError, match=f"field {field}"):
        cfg.validate()


def test_train_refuses_lie_poisson_options():
    with pytest.raises(ValueError, match="checkpoint is not supported"):
        train(_config(iterations=1), checkpoint="x", progress=False)


@pytest.mark.parametrize(("n", "slope"), [(3, 5), (4, 5)])
def test_casimir_defect_per_step_has_the_realization_order(n, slope):
    # C(β) − C(α) = O(|p|^{n+1}) (n even) or O(|p|^{n+2}) (n odd), p = ∇S = O(h): the one-step
    # Casimir defect of a model with a random network has the realization's order, not S's.
    s_fn = _random_network(_config(realization_order=n), seed=5)
    core = hj.core_model(s_fn)
    x = _states(32, 6).numpy()
    steps = 0.1 * 0.5 ** np.arange(4)
    c0 = NAMBU.casimirs(x)[:, 0]
    drift = [np.abs(NAMBU.casimirs(core.rollout(x, h, 1)[0][:, 1])[:, 0] - c0).max() for h in steps]
    fitted = np.polyfit(np.log(steps), np.log(drift), 1)[0]
    assert abs(fitted - slope) < 0.3, (fitted, drift)


def test_every_learned_realization_is_one_core_class_with_the_package_defaults():
    poly = hj.core_model(hj.build_model(_config()))
    log = pr.load_model("lotka_volterra_h01")._core
    assert type(poly) is type(log) is pr._core.LearnedModel
    assert (poly.realization, log.realization) == ("polynomial", "log_canonical")
    assert poly.metadata == {} and log.metadata["structure"] == "log_canonical"
    # One signature, whose Newton defaults are the package's (they had drifted apart).
    signature = pr._core.LearnedModel.rollout.__text_signature__
    assert f"tol={pr.NEWTON_TOL!r}, max_iter={pr.NEWTON_MAX_ITER}" in signature
    # Non-finite states are refused by name on every realization, before any step.
    for core in (poly, log):
        bad = np.full((2, core.dim), 0.5)
        bad[1, 0] = np.nan
        with pytest.raises(ValueError, match=r"x0 holds NaN or infinite values \(state 1\)"):
            core.rollout(bad, 0.1, 1)
