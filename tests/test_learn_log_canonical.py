"""Learning H on a known log-canonical structure from trajectories (PNN's Lotka–Volterra
protocol): the fit through the integrator sits at (or below) the true H's error through the
same integrator."""

from __future__ import annotations

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.learn.log_canonical import fit_lotka_volterra

C = [[0.0, 1.0], [-1.0, 0.0]]
LV = pr.lotka_volterra(C, [1.0, 2.0])
TRAIN = np.array([[1.0, 0.8], [1.0, 1.0], [1.0, 1.2]])  # PNN's states
HIDDEN = np.array([[1.0, 0.9], [1.0, 1.1], [0.8, 1.0]])


@pytest.fixture(scope="module")
def data() -> tuple[list[np.ndarray], np.ndarray]:
    reference = pr.classical(LV, "dop853", tol=1e-13)
    trajs = list(pr.integrate(reference, TRAIN, 0.1, 100))  # 100 training steps each
    return trajs, pr.integrate(reference, HIDDEN, 0.1, 1000)[:, -1]  # T = 100


@pytest.mark.parametrize("order", [3, 5])
def test_pnn_protocol_through_the_integrator_meets_the_true_h(
    data: tuple[list[np.ndarray], np.ndarray], order: int
) -> None:
    trajs, exact = data

    def error(stepper: object) -> float:
        end = pr.integrate(stepper, HIDDEN, 0.1, 1000)[:, -1]
        return float(np.linalg.norm(end - exact, axis=-1).max())

    truth = error(pr.taylor_integrator(LV, order))
    fitted = fit_lotka_volterra(trajs, 0.1, C, order=order)
    field_only = fit_lotka_volterra(trajs, 0.1, C, order=order, through_integrator=False)
    assert error(fitted.stepper) <= 1.2 * truth
    assert error(fitted.stepper) < error(field_only.stepper)
    # Still H = u − ln u + v − 2 ln v, up to what the integrator's own error shifts.
    np.testing.assert_allclose(fitted.a, [1.0, 1.0], atol=1e-4)
    np.testing.assert_allclose(fitted.b, [1.0, 2.0], atol=1e-4)


def test_window_is_checked(data: tuple[list[np.ndarray], np.ndarray]) -> None:
    with pytest.raises(ValueError, match="window"):
        fit_lotka_volterra(data[0], 0.1, C, window=0)
