"""The learned S for an expression H (poisson_rs.realizations.expression_hj): the bracket read
from the structure, the least-squares surrogate, the true-H residual, training, the core's step
of the result against torch's, and bad input."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import poisson_rs as pr
from poisson_rs.realizations import expression_hj as ehj
from poisson_rs.realizations import polynomial_hj as hj
from poisson_rs.scenes import load_scene

SCENES = "scenes"
PNN_H = "u**2/2 - cos(v) + u*(r - u**2 - v**2)"
POLY_H = "u**2/2 + v**2/2 - v**4/24 + u*(r - u**2 - v**2)"
LO, HI = (-0.4, -0.4, -0.1), (0.4, 0.4, 0.5)


@pytest.fixture(scope="module")
def pendulum() -> Any:
    return load_scene(f"{SCENES}/extended_pendulum_pnn.toml").system


def test_the_bracket_read_from_the_structure_is_the_structures_bivector(pendulum: Any) -> None:
    biv = ehj.polynomial_bracket(pendulum)
    x = np.random.default_rng(0).normal(size=(16, 3))
    assert np.abs(biv(x) - pendulum.bivector(x)).max() < 1e-14


def test_the_surrogate_of_a_polynomial_is_that_polynomial_and_stays_sparse(
    pendulum: Any,
) -> None:
    s: Any = pr.with_hamiltonian(pendulum.base, POLY_H)
    sur = ehj.fit_surrogate(s.h, 4, LO, HI)
    x = np.random.default_rng(1).uniform(LO, HI, size=(200, 3))
    assert sur.rms < 1e-12 and sur.max < 1e-11
    from poisson_rs.expressions import Expression, default_names

    back = Expression(sur.text, default_names(3))
    assert np.abs(back(x) - s.h(x)).max() < 1e-11
    # H has 6 monomials; the dropped noise terms leave exactly those.
    assert sur.text.count("+") + 1 == 6
    # One degree too low misses the quartic: the reported error says so.
    assert ehj.fit_surrogate(s.h, 3, LO, HI).rms > 1e-6


def test_the_true_h_residual_of_the_taylor_base_at_t0_is_h_minus_the_surrogate(
    pendulum: Any,
) -> None:
    """At t = 0, ∇S = 0 and β(x, 0) = x, so r(0, x) = −H_d(x) + H(x) exactly."""
    cfg = ehj.ExpressionTrainConfig.of(pendulum, x_min=LO, x_max=HI, widths=())
    model = hj.build_model(cfg)
    x = torch.tensor(np.random.default_rng(2).uniform(LO, HI, size=(64, 3)))
    r = ehj.expression_residual(model, cfg.hamiltonian(), torch.zeros(64, dtype=x.dtype), x)
    sur = cfg.surrogate()
    from poisson_rs.expressions import Expression, default_names

    h_d = Expression(sur.text, default_names(3))(x.numpy())
    want = pendulum.hamiltonian(x.numpy()) - h_d
    assert np.abs(r.numpy() - want).max() < 1e-13
    assert 1e-7 < np.abs(want).max() <= sur.max * 1.5


def test_on_a_polynomial_h_the_residual_is_the_polynomial_realizations(pendulum: Any) -> None:
    """The same S (random network, seeded) through the expression residual and through the
    polynomial path's term tables (an independent evaluation of H)."""
    s: Any = pr.with_hamiltonian(pendulum.base, POLY_H)
    cfg = ehj.ExpressionTrainConfig.of(s, x_min=LO, x_max=HI, widths=(8,), taylor_order=2)
    model = hj.build_model(cfg)
    torch.manual_seed(3)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(0.3 * torch.randn_like(p))
    gen = torch.Generator().manual_seed(4)
    t, x = hj.sample_points(cfg, 128, gen, torch.float64)
    a = ehj.expression_residual(model, cfg.hamiltonian(), t, x)
    b = hj.hj_residual(model, t, x)
    assert np.abs(a.detach().numpy() - b.detach().numpy()).max() < 1e-11
    assert np.abs(b.detach().numpy()).max() > 1e-3  # the network is not zero


def test_training_lowers_the_true_residual_and_the_core_steps_it_as_torch(
    pendulum: Any, tmp_path: Path
) -> None:
    torch.set_num_threads(1)
    cfg = ehj.ExpressionTrainConfig.of(
        pendulum, x_min=LO, x_max=HI, taylor_order=3, widths=(8, 8), iterations=150,
        batch=256, h_max=0.1, seed=0, lbfgs_iterations=100, lbfgs_batch=1024,
    )  # fmt: skip
    result = ehj.train_expression(cfg, progress=False)
    assert result.validation_rms < 0.5 * result.baseline_rms
    path = hj.save_result(result, tmp_path / "m.safetensors", name="t", command="test")
    data = path.read_bytes()
    stepper = pr.load_model(path)
    x0 = np.random.default_rng(5).uniform(0.5 * np.array(LO), 0.5 * np.array(HI), (16, 3))
    ours = pr.integrate(stepper, x0, 0.1, 1)[:, -1]
    theirs = hj.step_map(result.model, torch.tensor(x0), 0.1).numpy()
    assert np.abs(ours - theirs).max() < 1e-11
    # The file records what S was trained for (the expression) beside the surrogate it steps.
    import json

    meta = json.loads(data[8 : 8 + int.from_bytes(data[:8], "little")])["__metadata__"]
    assert json.loads(meta["config"])["expression"] == PNN_H


def test_bad_input_is_refused_naming_the_field(pendulum: Any) -> None:
    with pytest.raises(ValueError, match="field system"):
        ehj.ExpressionTrainConfig.of(load_scene(f"{SCENES}/nambu_cubic.toml").system,
                                     x_min=LO, x_max=HI)  # fmt: skip
    with pytest.raises(ValueError, match="system"):
        ehj.ExpressionTrainConfig.of(
            load_scene(f"{SCENES}/charged_particle_pnn.toml").system,
            x_min=(-1,) * 4,
            x_max=(1,) * 4,
        )
    bad: tuple[Any, ...] = (0, 7, 2.0, True)
    for degree in bad:
        with pytest.raises(ValueError, match="surrogate_degree"):
            ehj.ExpressionTrainConfig.of(pendulum, x_min=LO, x_max=HI, surrogate_degree=degree)
    with pytest.raises(ValueError, match="field x_min"):
        ehj.ExpressionTrainConfig.of(pendulum, x_min=(0, 0), x_max=HI)
    with pytest.raises(ValueError, match="field x_min"):
        ehj.ExpressionTrainConfig.of(pendulum, x_min=(0, float("nan"), 0), x_max=HI)
    with pytest.raises(ValueError, match="field x_max"):
        ehj.ExpressionTrainConfig.of(pendulum, x_min=HI, x_max=LO)
    with pytest.raises(ValueError, match="not finite"):
        ehj.ExpressionTrainConfig.of(
            pr.with_hamiltonian(pendulum.base, "log(u) + v**2"), x_min=LO, x_max=HI
        )
    cfg = ehj.ExpressionTrainConfig.of(pendulum, x_min=LO, x_max=HI)
    cfg.expression = "u + __import__"
    with pytest.raises(ValueError, match="field expression"):
        cfg.validate()
