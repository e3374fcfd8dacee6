"""What :func:`poisson_rs.learn` did: every candidate, the data's diagnostics, the kept one."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from ..structures.lie_poisson import LiePoissonSystem, Polynomial

__all__ = ["Candidate", "LearnReport"]


@dataclass
class Candidate:
    """One model tried.

    ``family``: "poly2", "poly3", "poly4" (H a polynomial of that degree) or "map" (a learned
    generating function of the time-h map); ``parameters``: non-zero coefficients or network
    weights; ``order``: the Taylor-HJ order K (0 for a map); ``seconds``: training time;
    ``one_step``: held-out RMS of |Φ(μ_k) − μ_{k+1}|/|μ_k|; ``rollout``: held-out max of
    |μ(t) − data(t)|/|data(t)| rolling each held-out trajectory out from its first record;
    ``kept``/``reason``: whether it was chosen, and why (or why not).
    """

    family: str
    parameters: int
    order: int
    seconds: float
    one_step: float
    rollout: float
    kept: bool = False
    reason: str = ""
    stepper: Any = field(default=None, repr=False)
    model_bytes: bytes = field(default=b"", repr=False)
    system: LiePoissonSystem | None = field(default=None, repr=False)


@dataclass
class LearnReport:
    """Result of :func:`poisson_rs.learn`.

    ``mode``: the mode asked for; ``candidates``: every model tried, in order; ``kept``: the
    chosen one; ``hamiltonian``: the learned H (a :class:`Polynomial`, gauge-fixed: no
    constant, no Casimir component) or None for a map; ``system``: the learned system or None;
    ``noise``: estimated noise level of the data, relative to its RMS |μ| (an upper bound; NaN
    when the records are too few to tell); ``casimir_drift``: the data's own largest relative
    Casimir drift (NaN when the algebra has no known Casimir); ``data_sha256``, ``data_shape``:
    what was learned from; ``threshold``: the held-out one-step error a candidate had to reach;
    ``held_out``: whether any records were held out (False: two trajectories, or one of a few
    records; the errors are then training errors, and the report says so); ``span``: the
    longest scored trajectory's duration, the horizon the rollout errors cover (nothing beyond
    it was checked).
    """

    mode: str
    candidates: list[Candidate]
    kept: Candidate
    noise: float
    casimir_drift: float
    data_sha256: str
    data_shape: tuple[int, int, int]
    threshold: float
    h: float
    seed: int
    held_out: bool = True
    span: float = math.nan

    @property
    def hamiltonian(self) -> Polynomial | None:
        return None if self.kept.system is None else self.kept.system.polynomial

    @property
    def system(self) -> LiePoissonSystem | None:
        return self.kept.system

    def rows(self) -> list[dict[str, Any]]:
        """The candidate table as JSON-safe rows."""
        return [
            {
                "family": c.family,
                "parameters": c.parameters,
                "order": c.order,
                "seconds": round(c.seconds, 3),
                "one_step": c.one_step,
                "rollout": c.rollout,
                "kept": c.kept,
                "reason": c.reason,
            }
            for c in self.candidates
        ]

    def __str__(self) -> str:
        def num(x: float) -> str:
            return "n/a" if not math.isfinite(x) else f"{x:.2e}"

        scored = "held-out" if self.held_out else "training"
        lines = [
            f"learn (mode {self.mode}): data {self.data_shape[0]} trajectories × up to "
            f"{self.data_shape[1]} records, dim {self.data_shape[2]}, h = {self.h:g}, seed "
            f"{self.seed}",
            f"  noise (relative, upper bound) {num(self.noise)}; data's Casimir drift "
            f"{num(self.casimir_drift)}; {scored} one-step threshold {num(self.threshold)}",
        ]
        if not self.held_out:
            lines.append(
                "  nothing held out (too few trajectories or records to split): the errors "
                "below are training errors, and the choice was made on them"
            )
        span = f"T = {self.span:g}" if math.isfinite(self.span) else "the records' span"
        lines += [
            f"  errors ({scored}): one step, and rollouts of the scored trajectories up to "
            f"{span}; nothing beyond {span} was checked",
            f"  {'family':<7} {'params':>6} {'K':>2} {'train s':>8} {'1-step':>9} "
            f"{'rollout':>9}  verdict",
        ]
        for c in self.candidates:
            verdict = ("KEPT: " if c.kept else "passed over: ") + c.reason
            lines.append(
                f"  {c.family:<7} {c.parameters:>6} {c.order:>2} {c.seconds:>8.2f} "
                f"{num(c.one_step):>9} {num(c.rollout):>9}  {verdict}"
            )
        if self.hamiltonian is not None:
            terms = ", ".join(f"{coef:+.6g}·μ^{e}" for e, coef in self.hamiltonian.terms.items())
            lines.append(f"  H = {terms}")
            lines.append(
                "  (gauge-fixed: no constant and no Casimir component, so it may differ from the "
                "true H by a Casimir function plus a constant, which change no trajectory)"
            )
        return "\n".join(lines)
