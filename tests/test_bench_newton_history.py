"""`benches/newton_history.py`: its replay of simplified Newton is the core's (the same update
counts, state by state), reaches the package's own solution, and a carried inverse skips the
Hessian passes only where it still contracts."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import poisson_rs as pr
from poisson_rs.generating import solve_momentum

ROOT = Path(__file__).resolve().parents[1]
# The benches are scripts, not part of the package: make their directory importable.
sys.path.insert(0, str(ROOT / "benches"))
import newton_history as nh  # noqa: E402
from newton_predictors import predict, series  # noqa: E402


@pytest.fixture(scope="module")
def rigid() -> tuple[object, torch.Tensor]:
    stepper = pr.taylor_integrator(pr.RigidBody((1.5, 2.0, 2.5)), 3, chart="exp")
    mu = torch.as_tensor(nh.rigid_states(12, np.random.default_rng(7)))
    return stepper, mu


def test_the_replay_counts_the_cores_updates_state_by_state(rigid: tuple) -> None:
    stepper, mu = rigid
    cheap = series(stepper.system, 3, stepper.chart)
    p0 = torch.stack([predict(stepper.system, cheap, stepper.chart, m, "hessian") for m in mu])
    _, _, updates, refreshes = nh.replay(stepper, mu, p0, None)
    _, info = pr.integrate(stepper, mu.numpy(), nh.H, 1, return_info=True)
    assert updates.tolist() == info.newton_iterations.tolist()
    assert bool((refreshes >= 1).all())  # a fresh Jacobian at the first update


def test_the_replay_reaches_the_packages_solution(rigid: tuple) -> None:
    stepper, mu = rigid
    ref, done = solve_momentum(stepper.generating, mu, nh.H, chart=stepper.chart, tol=stepper.tol)
    assert bool(done.all())
    p, _, _, _ = nh.replay(stepper, mu, mu.clone(), None)
    gap = ((p - ref).abs().amax(-1) / ref.abs().amax(-1)).max()
    assert float(gap) < 1e-11


def test_a_carried_inverse_is_kept_while_it_contracts(rigid: tuple) -> None:
    stepper, mu = rigid
    mus, ps = nh.reference(stepper, mu, 3)
    # The inverse of step 1's solve, carried into step 2: no Hessian pass there, and the same
    # solution to the tolerance.
    _, inv, _, fresh = nh.replay(stepper, mus[1], ps[0] - mus[0] + mus[1], None)
    p, _, updates, refreshes = nh.replay(stepper, mus[2], ps[1] - mus[1] + mus[2], inv)
    assert bool((fresh >= 1).all()) and int(refreshes.sum()) == 0
    assert bool((updates >= 2).all())
    assert float(((p - ps[2]).abs().amax(-1) / ps[2].abs().amax(-1)).max()) < 1e-11
    # Half the inverse contracts each update by about 1/2, worse than the rule's 1/4: the rule
    # refreshes (after the second update), and the solve still ends at the solution.
    p, _, _, refreshes = nh.replay(stepper, mus[2], mus[2].clone(), 0.5 * inv)
    assert bool((refreshes >= 1).all())
    assert float(((p - ps[2]).abs().amax(-1) / ps[2].abs().amax(-1)).max()) < 1e-11


def test_too_short_a_rollout_is_refused_before_any_work(tmp_path: Path) -> None:
    out = tmp_path / "history.json"
    script = str(ROOT / "benches" / "newton_history.py")
    run = subprocess.run(
        [sys.executable, script, "--steps", "3", "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert run.returncode != 0 and "--steps at least 4" in run.stderr
    assert "| stepper |" not in run.stdout and not out.exists()
