"""Scoring a learned stepper on held-out records, and the progress bar over planned fits:
shared by every path of :func:`poisson_rs.learn`."""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Any

import numpy as np

from ..rollout import integrate
from .data import TrajectoryData

__all__ = ["NoBar", "all_records", "errors", "one_step", "progress_bar"]


def one_step(stepper: Any, starts: np.ndarray, h: float) -> np.ndarray:
    """One step of ``stepper`` from each of ``starts`` (B, n) → (B, n); NaN rows where a step
    failed (warnings silenced: the caller scores the failure)."""
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        out = integrate(stepper, starts, h, 1, on_failure="ignore")
    return np.asarray(out)[:, -1]


def errors(stepper: Any, data: TrajectoryData) -> tuple[float, float]:
    """Held-out one-step RMS relative error and rollout max relative error (train data when
    nothing is held out)."""
    trajs = data.test or data.train
    starts = np.concatenate([t[:-1] for t in trajs])
    targets = np.concatenate([t[1:] for t in trajs])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = integrate(stepper, starts, data.h, 1, on_failure="ignore")[:, -1]
        rel = np.linalg.norm(out - targets, axis=1) / np.linalg.norm(starts, axis=1)
        one = float(np.sqrt(np.mean(rel**2)))
        worst = 0.0
        for t in trajs:
            roll = integrate(stepper, t[0], data.h, len(t) - 1, on_failure="ignore")
            e = np.linalg.norm(roll - t, axis=1) / np.linalg.norm(t, axis=1)
            top = float(np.max(e))
            # A failed rollout (NaN) is an infinite error, never hidden by max().
            worst = max(worst, top if math.isfinite(top) else math.inf)
    return (one if math.isfinite(one) else math.inf), (worst if math.isfinite(worst) else math.inf)


def all_records(data: TrajectoryData) -> TrajectoryData:
    """The same data with nothing held out (a single trajectory whole again)."""
    if not data.test:
        return data
    if data.shape[0] == 1:
        whole = [np.concatenate([data.train[0], data.test[0][1:]])]
    else:
        whole = data.train + data.test
    return dataclasses.replace(data, train=whole, test=[])


class NoBar:
    """What the fits call on a progress bar, doing nothing."""

    n = 0
    total = 0

    def set_postfix_str(self, s: str) -> None:
        pass

    def update(self, k: int) -> None:
        self.n += k

    def refresh(self) -> None:
        pass

    def close(self) -> None:
        pass


def progress_bar(total: int, progress: bool | None) -> Any:
    """A tqdm bar over the planned fits (ETA from the fits done so far), on stderr; none when
    ``progress`` is False, or None and stderr is not a terminal."""
    import sys

    if progress is None:
        progress = bool(getattr(sys.stderr, "isatty", lambda: False)())
    if not progress:
        return NoBar()
    from tqdm.auto import tqdm

    return tqdm(total=total, desc="learn", unit="fit", file=sys.stderr, leave=True)
