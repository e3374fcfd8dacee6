"""select(): the cheapest integrator and step that meet a target, measured on given states."""

from __future__ import annotations

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.studies.select import NoCandidateError

BODY = pr.RigidBody((1.5, 2.0, 2.5))


def shell_states(n: int, seed: int, r_min: float = 1.5, r_max: float = 2.9) -> np.ndarray:
    """n states with |μ| uniform in [r_min, r_max] and uniform directions: (n, 3)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * rng.uniform(r_min, r_max, size=(n, 1))


def relative_error(stepper: object, mu0: np.ndarray, h: float, T: float) -> float:
    traj = pr.integrate(stepper, mu0, h, round(T / h), every=round(T / h))
    exact = pr.exact_solution(BODY, mu0, [T])[:, 0]
    return float((np.linalg.norm(traj[:, -1] - exact, axis=1) / np.linalg.norm(mu0, axis=1)).max())


@pytest.mark.parametrize("target", [1e-4, 1e-7])
def test_selected_method_meets_the_target_on_held_out_states(target: float) -> None:
    mu0 = shell_states(8, seed=3)
    stepper, h, report = pr.select(BODY, mu0, T=2.0, target=target, models=["default"])
    winner = report.winner
    assert winner is not None and winner.passing is not None and winner.passing.h == h
    assert winner.passing.error <= target
    # The cheapest: no other passing candidate was measured cheaper.
    costs = [r.passing.seconds for r in report.results if r.passing is not None]
    assert winner.passing.seconds == min(costs)
    held_out = shell_states(8, seed=4)
    assert relative_error(stepper, held_out, h, 2.0) <= target
    table = str(report)
    assert "selected" in table and winner.name in table


def test_failing_rungs_never_pass_and_every_loser_says_why() -> None:
    # Large steps on fast states: the coarse rungs of the implicit methods fail (Newton), RK4's
    # blow up; none of those may count as passing.
    mu0 = shell_states(4, seed=5, r_min=8.0, r_max=9.0)
    _, _, report = pr.select(BODY, mu0, T=4.0, target=1e-3, models=[])
    failed = [t for r in report.results for t in r.trials if t.failure]
    assert failed, "expected some rung to fail at h = 1 with |mu| ~ 9"
    assert not any(t.passed for t in failed)
    for r in report.results:
        assert r.winner or r.excluded or r.reason


def test_learned_models_outside_their_domain_or_h_max_are_excluded() -> None:
    default = pr.load_model("default")  # shell 1 <= |mu| <= 4, h_max = 0.1
    far = shell_states(3, seed=6, r_min=5.0, r_max=6.0)
    _, _, report = pr.select(BODY, far, T=1.0, target=1e-3, models=[default])
    (res,) = [r for r in report.results if r.family == "learned"]
    assert "outside its training domain" in res.excluded and not res.trials
    near = shell_states(3, seed=6)
    _, _, report = pr.select(BODY, near, T=1.0, target=1e-3, h=0.25, models=[default])
    (res,) = [r for r in report.results if r.family == "learned"]
    assert "h_max" in res.excluded and not res.winner
    # Without h, its ladder starts at its h_max: no rung beyond it.
    _, _, report = pr.select(BODY, near, T=1.0, target=1e-3, models=[default])
    (res,) = [r for r in report.results if r.family == "learned"]
    assert res.trials and max(t.h for t in res.trials) <= default.h_max


def test_a_model_for_another_system_is_excluded() -> None:
    top = pr.HeavyTop()
    mu0 = np.array([[0.5, 0.3, 1.0, 0.0, 0.6, 0.8]])
    ref = pr.reference_solution(top, mu0, [1.0])[:, 0]
    _, _, report = pr.select(top, mu0, T=1.0, target=1e-3, models=["default"], reference=ref)
    (res,) = [r for r in report.results if r.family == "learned"]
    assert res.excluded.startswith("trained for RigidBody")
    names = {r.name for r in report.results}
    assert "taylor3-exp" in names and "taylor3-cayley" not in names and "splitting" in names


def test_impossible_target_raises_with_the_best_candidate() -> None:
    mu0 = shell_states(2, seed=7)
    with pytest.raises(ValueError, match=r"no candidate meets 1e-16 at T = 1; best was \S+ with"):
        pr.select(BODY, mu0, T=1.0, target=1e-16, models=[], max_steps=64)
    try:
        pr.select(BODY, mu0, T=1.0, target=1e-16, models=[], max_steps=64)
    except NoCandidateError as e:
        assert e.report.winner is None and len(e.report.results) > 5


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"T": 0.0, "target": 1e-3}, "T must be"),
        ({"T": 1.0, "target": -1.0}, "target must be"),
        ({"T": 1.0, "target": 1e-3, "h": 0.3}, "whole number of steps"),
    ],
)
def test_bad_arguments(kwargs: dict[str, float], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        pr.select(BODY, [[1.0, 1.0, 2.0]], **kwargs)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="shape"):
        pr.select(BODY, [[1.0, 1.0]], T=1.0, target=1e-3)


# --- metric: energy and Casimir over [0, T]; the budget inside a rollout -----------------------


def test_select_by_energy_meets_the_energy_target_on_held_out_states() -> None:
    mu0 = shell_states(4, seed=5)
    stepper, h, report = pr.select(
        BODY, mu0, T=5.0, target=1e-6, metric="energy", models=["default"], budget_s=5
    )
    assert report.metric == "energy" and report.reference == "none needed"
    assert "max |H - H0|/|H0| over [0, T] <= 1e-06" in report.table()
    # Independent check: the energy error of the selected method over every step.
    held_out = shell_states(4, seed=6)
    traj = pr.integrate(stepper, held_out, h, round(5.0 / h))
    e = BODY.hamiltonian(traj)
    assert float((np.abs(e - e[:, :1]) / e[:, :1]).max()) <= 3e-6  # records vs every step


def test_select_by_casimir_needs_a_known_casimir() -> None:
    c = np.zeros((3, 3, 3))
    c[2, 0, 0], c[0, 2, 0] = 1.0, -1.0
    c[2, 1, 1], c[1, 2, 1] = 1.0, -1.0
    h = pr.Polynomial({(2, 0, 0): 0.5, (0, 2, 0): 0.5, (0, 0, 2): 0.5})
    system = pr.LiePoissonSystem(pr.LieAlgebra(c), h)
    with pytest.raises(ValueError, match="no Casimir"):
        pr.select(system, [1.0, 0.5, 0.2], T=1.0, target=1e-6, metric="casimir")
    with pytest.raises(ValueError, match="metric"):
        pr.select(BODY, [1.0, 0.5, 0.2], T=1.0, target=1e-6, metric="speed")
    _, _, report = pr.select(BODY, [1.0, 0.5, 0.2], T=1.0, target=1e-12, metric="casimir",
                             models=[], budget_s=2)  # fmt: skip
    winner = report.winner
    assert winner is not None and winner.passing is not None
    assert winner.passing.casimir <= 1e-12


def test_a_chaotic_horizon_gets_a_useful_answer() -> None:
    # The heavy top to T = 200: no fixed-step method keeps a pointwise error of 1e-8 there (the
    # DOP853 reference itself separates), but energy and Casimirs still rank the methods.
    top = pr.HeavyTop()
    mu0 = np.array([[1.0, -0.5, 0.2, 0.6, 0.0, 0.8]])
    with pytest.raises(NoCandidateError) as info:
        pr.select(top, mu0, T=200.0, target=1e-14, models=[], budget_s=1.0, max_steps=4096)
    message = str(info.value)
    assert "metric='energy' or 'casimir'" in message
    assert "best by energy:" in message and "best by casimir:" in message


def test_the_budget_holds_inside_one_rollout() -> None:
    # T = 1e6: the coarsest rung alone is 10⁶ steps of each state; a candidate whose first
    # rung the budget cannot pay for is not run at all (priced by a 16-step probe).
    mu0 = shell_states(2, seed=1)
    with pytest.raises(NoCandidateError) as info:
        pr.select(BODY, mu0, T=1e6, target=1e-3, models=[], budget_s=0.05, max_steps=1 << 30)
    report = info.value.report
    slow = [r for r in report.results if r.name in ("taylor7-cayley", "dop853")]
    assert slow and all(r.stopped == "budget" and not r.trials for r in slow)
    assert all("time budget" in r.reason for r in slow)
    # max_steps bounds the ladder: T = 1e9 with at most 2^20 steps runs nothing.
    with pytest.raises(NoCandidateError) as info:
        pr.select(BODY, mu0, T=1e9, target=1e-3, models=[], budget_s=1.0)
    assert all(not r.trials for r in info.value.report.results)
    with pytest.raises(ValueError, match="budget_s"):
        pr.select(BODY, mu0, T=1.0, target=1e-3, budget_s=0.0)
