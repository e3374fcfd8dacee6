"""What :func:`poisson_rs.learn` did: every candidate, the data's diagnostics, the kept one."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from ..structures.lie_poisson import Polynomial

__all__ = ["Candidate", "LearnReport"]


@dataclass
class Candidate:
    """One model tried.

    ``family``: "poly2", "poly3", "poly4" (H a polynomial of that degree) or "map" (a learned
    generating function of the time-h map); ``parameters``: non-zero coefficients or network
    weights; ``order``: the Taylor-HJ order K (0 for a map); ``seconds``: training time;
    ``one_step``: held-out RMS of |Φ(μ_k) − μ_{k+1}|/|μ_k|; ``rollout``: held-out max of
    |μ(t) − data(t)|/|data(t)| rolling each held-out trajectory out from its first record;
    ``kept``/``reason``: whether it was chosen, and why (or why not); ``hamiltonian_family``,
    ``hamiltonian_text``, ``gauge``: on a structure learned through its own family (any but
    T*G), what H ranged over, the learned H as text, and what H is identifiable up to besides
    a constant; ``bracket_family``, ``bracket_text``, ``jacobi_residual``,
    ``velocity_residual``, ``casimirs_text``: with the structure discovered, what the bracket
    ranged over, the learned bracket as formulas, its Jacobi residual after the projection
    (relative), the velocity-level fit's relative residual, the learned structure's Casimirs,
    and the bracket coefficients' directions N (N∇H ≡ 0 on the data) the bracket may move along.
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
    system: Any = field(default=None, repr=False)
    hamiltonian_family: str = ""
    hamiltonian_text: str = ""
    gauge: str = ""
    fit: Any = field(default=None, repr=False)
    bracket_family: str = ""
    bracket_text: str = ""
    jacobi_residual: float = math.nan
    velocity_residual: float = math.nan
    casimirs_text: str = ""
    null_directions: list[Any] = field(default_factory=list, repr=False)


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
    it was checked); ``explained``: False where no candidate reached the noise level (the kept
    one is then only the best tried, and the data may not come from any family tried).
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
    explained: bool = True

    @classmethod
    def of(
        cls,
        data: Any,
        *,
        mode: str,
        candidates: list[Candidate],
        kept: Candidate,
        threshold: float,
        seed: int,
        explained: bool = True,
    ) -> LearnReport:
        """The report of a fit to ``data`` (a :class:`~poisson_rs.learn.data.TrajectoryData`):
        its diagnostics, digest and split read off it."""
        return cls(
            mode=mode,
            candidates=candidates,
            kept=kept,
            noise=data.noise,
            casimir_drift=data.casimir_drift,
            data_sha256=data.digest,
            data_shape=data.shape,
            threshold=threshold,
            h=data.h,
            seed=seed,
            held_out=bool(data.test),
            span=data.h * (max(len(t) for t in data.test or data.train) - 1),
            explained=explained,
        )

    @property
    def hamiltonian(self) -> Polynomial | None:
        """The learned H as a :class:`Polynomial` where the system holds one (Lie–Poisson,
        affine), else None (see :attr:`hamiltonian_text`)."""
        return getattr(self.kept.system, "polynomial", None)

    @property
    def hamiltonian_text(self) -> str:
        """The learned H as text ("" for a map)."""
        if self.kept.hamiltonian_text:
            return self.kept.hamiltonian_text
        poly = self.hamiltonian
        return "" if poly is None else " + ".join(f"{c!r}*mu^{e}" for e, c in poly.terms.items())

    @property
    def hamiltonian_family(self) -> str:
        """What H ranged over ("" where the Lie–Poisson path fitted it)."""
        return self.kept.hamiltonian_family

    @property
    def gauge(self) -> str:
        """What the learned H may differ from the true one by (besides a constant)."""
        return self.kept.gauge or ("a Casimir of the algebra" if self.hamiltonian else "")

    @property
    def system(self) -> Any:
        """The learned system (the structure with the learned H), or None for a map."""
        return self.kept.system

    @property
    def structure(self) -> Any:
        """The learned Poisson system (:class:`poisson_rs.PoissonSystem`, every tool takes
        it): the same as :attr:`system`."""
        return self.kept.system

    @property
    def bracket(self) -> str:
        """The discovered bracket as formulas ("" where the structure was given)."""
        return self.kept.bracket_text

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
                **(
                    {
                        "bracket": c.bracket_text,
                        "velocity_residual": c.velocity_residual,
                        "jacobi_residual": c.jacobi_residual,
                    }
                    if self.mode.startswith("discover")
                    else {}
                ),
            }
            for c in self.candidates
        ]

    def __str__(self) -> str:
        def num(x: float) -> str:
            return "n/a" if not math.isfinite(x) else f"{x:.2e}"

        scored = "held-out" if self.held_out else "training"
        width = max([7, *(len(c.family) for c in self.candidates)])
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
            f"  {'family':<{width}} {'params':>6} {'K':>2} {'train s':>8} {'1-step':>9} "
            f"{'rollout':>9}  verdict",
        ]
        for c in self.candidates:
            verdict = ("KEPT: " if c.kept else "passed over: ") + c.reason
            lines.append(
                f"  {c.family:<{width}} {c.parameters:>6} {c.order:>2} {c.seconds:>8.2f} "
                f"{num(c.one_step):>9} {num(c.rollout):>9}  {verdict}"
            )
        if not self.explained:
            lines.append(
                "  NOT EXPLAINED: no candidate reached the data's noise level; the kept one is "
                "only the best tried (the data may not come from any family tried)"
            )
        if self.kept.bracket_text:
            lines.append(f"  bracket family: {self.kept.bracket_family}")
            lines.append(f"  bracket: {self.kept.bracket_text}")
            lines.append(
                f"  Jacobi residual (relative, after projection): "
                f"{num(self.kept.jacobi_residual)}; Casimirs: {self.kept.casimirs_text}"
            )
        if self.kept.hamiltonian_text:
            lines.append(f"  H family: {self.kept.hamiltonian_family}")
            lines.append(f"  H = {self.kept.hamiltonian_text}")
            lines.append(
                f"  (gauge: H is identifiable only up to a constant and {self.kept.gauge}; the "
                "learned H may differ from the true one by those, which change no trajectory)"
            )
        elif self.hamiltonian is not None:
            terms = ", ".join(f"{coef:+.6g}·μ^{e}" for e, coef in self.hamiltonian.terms.items())
            lines.append(f"  H = {terms}")
            lines.append(
                "  (gauge-fixed: no constant and no Casimir component, so it may differ from the "
                "true H by a Casimir function plus a constant, which change no trajectory)"
            )
        return "\n".join(lines)
