"""Learned generating functions on the exact log-canonical groupoid: the HJ residual (fitted
order of the exact Taylor terms), training, the model file, the Rust step against the torch step,
the Casimirs, and bad input."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
import torch

import poisson_rs as pr
from poisson_rs.export import safetensors_bytes
from poisson_rs.integrators import LearnedLogCanonicalIntegrator
from poisson_rs.realizations import log_canonical_hj as hj
from poisson_rs.train import TrainConfig, train
from poisson_rs.untrusted import InputError

PNN = pr.lotka_volterra([[0, 1], [-1, 0]], [1, 2])
#: A 3D Lotka–Volterra system with the Casimir ln x₁ + ln x₂ + ln x₃ (c k = 0 for k = (1, 1, 1)).
LV3 = pr.lotka_volterra([[0, 1, -1], [-1, 0, 1], [1, -1, 0]], [1.0, 1.5, 2.0])


def _random_network(
    cfg: hj.LogCanonicalTrainConfig, seed: int, gain: float
) -> hj.LogCanonicalGenerating:
    """The configuration's model with every layer (the last included) drawn at random: a
    network that really contributes to S, for the step-map and Casimir tests."""
    s_fn = hj.build_model(cfg)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for layer in s_fn.linears:
            layer.weight.copy_(
                gain * torch.randn(layer.weight.shape, generator=gen, dtype=torch.float64)
            )
            layer.bias.copy_(
                0.3 * torch.randn(layer.bias.shape, generator=gen, dtype=torch.float64)
            )
    return s_fn


def _residual_slope(order: int, times: np.ndarray) -> np.ndarray:
    s_fn = hj.LogCanonicalGenerating(PNN, order, (), order + 2, np.zeros(2), np.ones(2), 0.1)
    q = torch.tensor([[0.1, 0.3], [-0.5, 1.0], [0.6, -0.2]], dtype=torch.float64)
    r = np.array(
        [
            hj.hj_residual(s_fn, PNN, torch.full((3,), float(t), dtype=torch.float64), q)
            .abs()
            .numpy()
            for t in times
        ]
    )
    return np.array([np.polyfit(np.log(times), np.log(r[:, j]), 1)[0] for j in range(3)])


@pytest.mark.parametrize(("order", "times"), [(1, 0.01), (3, 0.02), (5, 0.2)])
def test_taylor_terms_leave_a_residual_of_order_t_to_the_order_plus_one(order, times):
    # S_{K+1} = 0 for odd K on Lotka–Volterra, so the residual of the truncated series is
    # −(K + 2) t^{K+1} S_{K+2} + O(t^{K+2}): fitted slope K + 1.
    slopes = _residual_slope(order, times * 0.5 ** np.arange(4))
    assert np.all(np.abs(slopes - (order + 1)) < 0.1), slopes


def test_default_network_power_skips_the_vanishing_even_term():
    cfg = hj.LogCanonicalTrainConfig(PNN, taylor_order=3)
    assert cfg.resolved_mlp_power() == 5
    assert hj.LogCanonicalTrainConfig(PNN, taylor_order=3, mlp_power=4).resolved_mlp_power() == 4


def test_untrained_model_is_the_taylor_series_in_rust():
    # The network starts at zero output: the learned integrator steps like Taylor-HJ of the
    # same order (the same map, though a different expression of S).
    cfg = hj.LogCanonicalTrainConfig(PNN, taylor_order=3, widths=(4,))
    model = LearnedLogCanonicalIntegrator(hj.model_bytes(hj.build_model(cfg), cfg))
    x0 = np.array([[1.0, 0.8], [1.0, 1.2]])
    a = pr.integrate(model, x0, h=0.1, n_steps=50)
    b = pr.integrate(pr.log_canonical_taylor(PNN, 3), x0, h=0.1, n_steps=50)
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=0)


@pytest.mark.parametrize("system", [PNN, LV3], ids=["pnn2d", "lv3d"])
def test_rust_derivatives_and_step_equal_torch(system):
    n = system.dim
    cfg = hj.LogCanonicalTrainConfig(
        system, taylor_order=3, widths=(7, 5), x_min=(0.3,) * n, x_max=(3.0,) * n
    )
    s_fn = _random_network(cfg, seed=11, gain=0.7)
    model = LearnedLogCanonicalIntegrator(hj.model_bytes(s_fn, cfg))
    rng = np.random.default_rng(5)
    q = np.log(rng.uniform(0.4, 2.5, size=(64, n)))
    qt = torch.tensor(q)
    # ∂S/∂q and ∂²S/∂q² from the Rust duals against torch autograd.
    s, g, hs = model.derivatives(0.1, q)
    t = torch.full((len(q),), 0.1, dtype=torch.float64)
    qv = qt.clone().requires_grad_(True)
    s_t = s_fn(t, qv)
    (g_t,) = torch.autograd.grad(s_t.sum(), qv, create_graph=True)
    h_t = torch.stack(
        [torch.autograd.grad(g_t[:, i].sum(), qv, retain_graph=True)[0] for i in range(n)], 1
    )
    np.testing.assert_allclose(s, s_t.detach().numpy(), rtol=0, atol=1e-13)
    np.testing.assert_allclose(g, g_t.detach().numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(hs, h_t.detach().numpy(), rtol=0, atol=1e-12)
    # One step in Rust (x in, x out) against the torch Newton step in q.
    x1 = pr.integrate(model, np.exp(q), h=0.1, n_steps=1)[:, 1]
    q1 = hj.step_map(s_fn, system, qt, 0.1).numpy()
    assert np.isfinite(q1).all()
    assert np.abs(np.log(x1) - q1).max() <= 1e-11


def test_casimir_is_kept_to_round_off_whatever_the_network():
    n = LV3.dim
    cfg = hj.LogCanonicalTrainConfig(
        LV3, taylor_order=1, widths=(6,), x_min=(0.3,) * n, x_max=(3.0,) * n
    )
    model = LearnedLogCanonicalIntegrator(hj.model_bytes(_random_network(cfg, 3, 1.0), cfg))
    x0 = np.array([[1.0, 0.8, 1.3], [0.6, 1.1, 1.5]])
    traj = pr.integrate(model, x0, h=0.05, n_steps=2000)
    c = LV3.casimirs(traj)[..., 0]
    assert np.abs(c - c[:, :1]).max() <= 1e-12
    # The network really moved the map: it differs from the bare Taylor series.
    bare = pr.integrate(pr.log_canonical_taylor(LV3, 1), x0, h=0.05, n_steps=2000)
    assert np.abs(traj - bare).max() > 1e-3


def test_training_improves_on_its_taylor_base_and_is_seeded():
    cfg = hj.LogCanonicalTrainConfig(PNN, widths=(8, 8), iterations=300, batch=256, seed=4)
    a = train(cfg, progress=False, threads=1)
    b = train(cfg, progress=False, threads=1)
    assert a.losses == b.losses
    assert a.validation_rms < 0.85 * a.baseline_rms
    assert a.iterations_run == 300


def test_model_file_round_trip(tmp_path):
    cfg = hj.LogCanonicalTrainConfig(PNN, widths=(5,), iterations=20, batch=64)
    result = hj.train_log_canonical(cfg, progress=False)
    path = hj.save_result(result, tmp_path / "lv.safetensors", name="lv-test", command="test")
    model = pr.load_model(path)
    assert isinstance(model, LearnedLogCanonicalIntegrator)
    assert model.system == PNN and model.name == "lv-test" and model.mlp_power == 5
    assert model.h_max == 0.1 and model.taylor_order == 3
    x0 = np.array([1.0, 1.0])
    a = pr.integrate(model, x0, h=0.1, n_steps=20)
    b = pr.integrate(pickle.loads(pickle.dumps(model)), x0, h=0.1, n_steps=20)
    np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="h_max"):
        pr.integrate(model, x0, h=0.2, n_steps=1)


# ---------------------------------------------------------------------------------------------
# Bad input: one clear error each
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("system", [PNN, PNN.to_dict()], ids=["object", "dict"])
def test_lie_poisson_config_refuses_a_log_canonical_system(system):
    with pytest.raises(ValueError, match="LogCanonicalTrainConfig"):
        train(TrainConfig(system=system), progress=False)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"x_min": (0.0, 1.0)}, "x_min"),
        ({"x_max": (1.0, 2.0, 3.0)}, "x_max"),
        ({"x_min": (2.0, 2.0), "x_max": (1.0, 3.0)}, "x_max"),
        ({"taylor_order": 0}, "taylor_order"),
        ({"widths": (0,)}, "widths"),
        ({"h_max": float("nan")}, "h_max"),
        ({"system": {"kind": "log_canonical"}}, "system"),
    ],
)
def test_log_canonical_config_names_the_bad_field(change, field):
    cfg = hj.LogCanonicalTrainConfig(**{"system": PNN, **change})
    with pytest.raises(ValueError, match=field):
        cfg.validate()


def test_train_refuses_lie_poisson_only_options():
    cfg = hj.LogCanonicalTrainConfig(PNN, iterations=1)
    with pytest.raises(ValueError, match="checkpoint"):
        train(cfg, progress=False, checkpoint="x.pt")


def _lc_file(tmp_path, structure: str) -> str:
    cfg = hj.LogCanonicalTrainConfig(PNN, widths=(3,))
    data = hj.model_bytes(hj.build_model(cfg), cfg)
    size = int.from_bytes(data[:8], "little")
    import json

    header = json.loads(data[8 : 8 + size])
    meta = header.pop("__metadata__")
    meta["structure"] = structure
    base = 8 + size
    tensors = {}
    for name, entry in header.items():
        a, b = entry["data_offsets"]
        dtype = {"F64": "<f8", "I64": "<i8"}[entry["dtype"]]
        tensors[name] = np.frombuffer(data[base + a : base + b], dtype=dtype).reshape(
            entry["shape"]
        )
    path = tmp_path / f"{structure}.safetensors"
    path.write_bytes(safetensors_bytes(tensors, meta))
    return str(path)


def test_unknown_structure_is_one_clear_error(tmp_path):
    with pytest.raises(ValueError, match="unknown model structure 'nambu'"):
        pr.load_model(_lc_file(tmp_path, "nambu"))


def test_lie_poisson_loader_refuses_a_log_canonical_file(tmp_path):
    path = _lc_file(tmp_path, "log_canonical")
    with pytest.raises(ValueError, match="structure is 'log_canonical'"):
        pr.LearnedIntegrator(__import__("pathlib").Path(path))
    with pytest.raises(ValueError, match="'structure' is missing"):
        pr._core.LearnedModel.from_log_canonical_bytes(pr.taylor_integrator(order=1)._bytes)


def _edited_file(tmp_path, *, meta=None, drop=()) -> str:
    """A log-canonical model file (the untrained PNN model with widths (3,)) whose metadata is
    changed by ``meta`` and loses the keys in ``drop``."""
    cfg = hj.LogCanonicalTrainConfig(PNN, widths=(3,))
    data = hj.model_bytes(hj.build_model(cfg), cfg)
    size = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + size])
    raw = {**header.pop("__metadata__"), **(meta or {})}
    for key in drop:
        raw.pop(key)
    base = 8 + size
    tensors = {}
    for name, entry in header.items():
        a, b = entry["data_offsets"]
        dtype = {"F64": "<f8", "I64": "<i8"}[entry["dtype"]]
        tensors[name] = np.frombuffer(data[base + a : base + b], dtype=dtype).reshape(
            entry["shape"]
        )
    path = tmp_path / "edited.safetensors"
    path.write_bytes(safetensors_bytes(tensors, raw))
    return str(path)


_OTHER_B = pr.lotka_volterra([[0, 1], [-1, 0]], [1, 3]).to_dict()
#: The same structure and b, H = 2u + v − ln u − 2 ln v: only the polynomial part differs.
_OTHER_A = {
    **PNN.to_dict(),
    "hamiltonian": {"terms": [[[0, 1], 1.0], [[1, 0], 2.0]], "b": [1.0, 2.0]},
}


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"meta": {"system": json.dumps(_OTHER_B)}}, "system"),
        ({"meta": {"system": json.dumps(_OTHER_A)}}, "system"),
        ({"meta": {"taylor_order": "2"}}, "taylor_order"),
        ({"meta": {"taylor_order": "60"}}, "taylor_order"),
        ({"meta": {"widths": "[4]"}}, "widths"),
        ({"drop": ("mlp_power",)}, None),
    ],
    ids=["b", "polynomial-part", "taylor_order", "taylor_order-huge", "widths", "mlp_power"],
)
def test_metadata_that_disagrees_with_the_tensors_is_refused(tmp_path, change, field):
    # The core steps the file's Taylor terms and network; ``model.system`` is what the studies
    # score: metadata naming another H would integrate one system and report another.
    path = _edited_file(tmp_path, **change)
    with pytest.raises(InputError) as err:
        pr.load_model(path)
    assert path in err.value.source
    if field is None:  # the core's own check names the key in its message
        assert "mlp_power" in str(err.value)
    else:
        assert err.value.field == field


@pytest.mark.parametrize("x0", [[1.0, -0.5], [0.0, 1.0], [[1.0, 1.0], [2.0, -1e-3]]])
def test_states_outside_the_orthant_are_refused(x0):
    cfg = hj.LogCanonicalTrainConfig(PNN, widths=(3,))
    model = LearnedLogCanonicalIntegrator(hj.model_bytes(hj.build_model(cfg), cfg))
    with pytest.raises(ValueError, match="positive orthant"):
        pr.integrate(model, x0, h=0.1, n_steps=1)


def test_shipped_model_beats_its_taylor_base_on_the_pnn_scene():
    # The rule for a shipped network: it must beat the Taylor terms it is built on. Error at
    # PNN's horizon (1500 steps of h = 0.1) against a tight DOP853 reference.
    model = pr.load_model("lotka_volterra_h01")
    assert isinstance(model, LearnedLogCanonicalIntegrator)
    assert model.system == PNN and model.taylor_order == 3 and model.n_parameters == 41
    assert "benches/learned_log_canonical.py" in model.metadata["command"]
    assert model.metadata["seed"] == "0"
    x0 = np.array([[1.0, 0.8], [1.0, 1.0], [1.0, 1.2]])
    ref = pr.integrate(
        pr.log_canonical_classical(PNN, "dop853", tol=1e-13), x0, h=0.1, n_steps=1500
    )
    learned = pr.integrate(model, x0, h=0.1, n_steps=1500)
    taylor = pr.integrate(pr.log_canonical_taylor(PNN, 3), x0, h=0.1, n_steps=1500)
    err_learned = np.abs(learned[:, -1] - ref[:, -1]).max()
    err_taylor = np.abs(taylor[:, -1] - ref[:, -1]).max()
    assert err_learned < err_taylor / 30


def test_reading_the_structure_never_blocks_on_a_fifo(tmp_path):
    # load_model reads the header to find the structure before the loader's own checks: a FIFO
    # must still get the loader's error, not hang the call.
    import os

    fifo = tmp_path / "model.safetensors"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match="FIFO"):
        pr.load_model(fifo)
