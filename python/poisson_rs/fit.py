"""The one training stack every learned S shares: the configuration's optimiser fields
(:class:`FitConfig`), the Adam loop (:func:`adam_loop`) and the L-BFGS polish
(:func:`lbfgs_polish`).

A trainer (:mod:`poisson_rs.train` for Lie–Poisson generating functions,
:mod:`poisson_rs.realizations.pinn` for the learned realizations) supplies its model's
parameters and its objective; the schedule, the logging, the progress bar, the time limit and
the polish are here, once, so that the same seed takes the same steps whichever trainer runs.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

#: objective(i) → (the normalised loss to minimise, the loss to report in absolute units) at
#: Adam iteration i; it draws its own batch, so that the random stream stays the trainer's.
Objective = Callable[[int], tuple[Tensor, Tensor]]

#: SCHEDULES: "cosine" decays to 1 % of lr (most of the final accuracy comes from the small-lr
#: tail), "constant" keeps lr.
SCHEDULES = ("cosine", "constant")


class FitConfig:
    """The fields of a training configuration the loop and the polish read, and the schedule.

    Every training configuration (:class:`poisson_rs.train.TrainConfig`,
    :class:`~poisson_rs.realizations.log_canonical_hj.LogCanonicalTrainConfig`,
    :class:`~poisson_rs.realizations.polynomial_hj.PolynomialTrainConfig`) is one. The fields are
    declared by each configuration's dataclass (with its own defaults and in its own order, which
    its recorded JSON keeps); this base only names them, so it adds no dataclass field.
    """

    seed: int
    iterations: int
    batch: int
    lr: float
    schedule: str
    dtype: str
    lbfgs_iterations: int

    def torch_dtype(self) -> torch.dtype:
        """``dtype`` as a torch dtype."""
        dtype = getattr(torch, self.dtype)
        assert isinstance(dtype, torch.dtype)
        return dtype

    def lr_at(self, i: int) -> float:
        """Adam's learning rate at iteration ``i`` under ``schedule``."""
        if self.schedule == "constant":
            return self.lr
        return self.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * i / max(self.iterations, 1))))

    def polish_batch(self) -> int:
        """How many points L-BFGS polishes on (one fixed seeded batch): ``batch`` unless the
        configuration sets its own."""
        return self.batch


# Seeds derived from ``seed``, one per random stream, so that the streams are independent and a
# run is a function of its configuration alone.
SCALE_SEED = 104729
"""Offset of the points the loss is normalised on before training."""
VALIDATION_SEED = 7919
"""Offset of the held-out validation points."""
POLISH_SEED = 31337
"""Offset of the L-BFGS batch."""
VALIDATION_POINTS = 8192
SCALE_POINTS = 4096


def is_int(v: Any) -> bool:
    """An integer that is not a bool (NumPy integers included)."""
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def check_run_options(log_every: Any, max_seconds: Any) -> None:
    """ValueError naming ``log_every`` (an integer ≥ 1) or ``max_seconds`` (None or > 0)."""
    if not is_int(log_every) or log_every < 1:
        raise ValueError(f"log_every must be an integer >= 1, got {log_every!r}")
    if max_seconds is not None and not (
        isinstance(max_seconds, (int, float))
        and not isinstance(max_seconds, bool)
        and max_seconds > 0
    ):
        raise ValueError(f"max_seconds must be a number > 0, got {max_seconds!r}")


@dataclass
class AdamRun:
    """How :func:`adam_loop` went."""

    losses: list[float] = field(default_factory=list)
    """The reported loss every ``log_every`` iterations and at the last one."""
    done: int = 0
    """Iterations taken, those before ``start`` included (0 for a model without parameters)."""
    timed_out: bool = False
    stopped_early: bool = False
    """``stop`` fired before the last iteration, or the time ran out."""
    t0: float = 0.0
    """``time.perf_counter()`` at the run's start, less the seconds already spent before
    ``start``: ``perf_counter() - t0`` is the run's time so far."""


def adam_loop(
    cfg: FitConfig,
    opt: torch.optim.Optimizer,
    objective: Objective,
    *,
    start: int = 0,
    losses: Sequence[float] = (),
    elapsed: float = 0.0,
    progress: bool = True,
    log_every: int = 10,
    callback: Callable[[int, float], None] | None = None,
    max_seconds: float | None = None,
    after_step: Callable[[int, AdamRun], None] | None = None,
    stop: Callable[[int], bool] | None = None,
) -> AdamRun:
    """Adam iterations ``start`` .. ``cfg.iterations`` − 1 on ``objective`` with the learning
    rate of ``cfg.lr_at``; none where ``opt`` has no parameters.

    ``losses`` and ``elapsed`` are what a resumed run had before ``start``. ``callback(i, loss)``
    sees each logged loss; ``after_step(i, run)`` runs after every iteration (a checkpoint);
    ``stop(done)`` ends the run when it returns True; ``max_seconds`` ends it cleanly between
    iterations. ``progress`` shows a tqdm bar."""
    n_params = sum(p.numel() for g in opt.param_groups for p in g["params"])
    if not n_params:
        start = cfg.iterations
    run = AdamRun(list(losses), start if n_params else 0, t0=time.perf_counter() - elapsed)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.iterations, initial=start, desc="train", unit="it", leave=True)
    wall0 = time.perf_counter()
    for i in range(start, cfg.iterations):
        if max_seconds is not None and time.perf_counter() - wall0 >= max_seconds:
            # Between iterations: the model is a consistent Adam state.
            run.timed_out = run.stopped_early = True
            break
        for g in opt.param_groups:
            g["lr"] = cfg.lr_at(i)
        opt.zero_grad(set_to_none=True)
        total, loss = objective(i)
        total.backward()
        opt.step()
        if i % log_every == 0 or i == cfg.iterations - 1:
            value = float(loss.detach())
            run.losses.append(value)
            if bar is not None:
                bar.set_postfix(loss=f"{value:.3e}", refresh=False)
            if callback is not None:
                callback(i, value)
        if bar is not None:
            bar.update(1)
        if after_step is not None:
            after_step(i, run)
        run.done = i + 1
        if stop is not None and stop(run.done):
            run.stopped_early = run.done < cfg.iterations
            break
    if bar is not None:
        bar.close()
    return run


def lbfgs_polish(
    params: Sequence[torch.nn.Parameter],
    objective: Callable[[], tuple[Tensor, Tensor]],
    iterations: int,
    *,
    start: float,
    record: list[float] | None = None,
) -> int:
    """L-BFGS (strong Wolfe) for ``iterations`` on ``objective()`` → (loss to minimise, loss to
    report), on one fixed batch the objective holds; returns the iterations taken. ``record``
    gets the reported loss at every evaluation, line-search trials included.

    torch's L-BFGS thresholds are absolute (a curvature pair counts only if yᵀs > 1e-10, it stops
    at |g|∞ ≤ tolerance_grad): the objective is divided by ``start``, its value at the start of
    polishing, which does not move its minimiser, so that those thresholds mean the same after
    any Adam phase."""
    scale = start if math.isfinite(start) and start > 0 else 1.0
    params = list(params)
    opt = torch.optim.LBFGS(
        params,
        lr=1.0,
        max_iter=iterations,
        max_eval=25 * iterations,
        tolerance_grad=1e-12,
        tolerance_change=1e-15,
        history_size=50,
        line_search_fn="strong_wolfe",
    )

    def closure() -> Tensor:
        opt.zero_grad(set_to_none=True)
        total, loss = objective()
        if record is not None:
            record.append(float(loss.detach()))
        total = total / scale
        total.backward()
        return total.detach()

    opt.step(closure)
    return int(opt.state[params[0]].get("n_iter", 0))
