"""The learned S for a Hamiltonian that is not a polynomial (an expression,
:mod:`poisson_rs.expressions`) on the order-n realization of the structure's polynomial bracket.

The core steps a learned S on that realization when S's Taylor part is a polynomial in x
(:mod:`.polynomial_hj`). For an expression H the exact Taylor terms are not polynomials, so the
Taylor part is taken from a *surrogate*: the least-squares polynomial H_d of degree d fitted to
H over the training box. The network then learns what the surrogate misses, on the HJ residual of
the true H,

    r(t, x) = ∂S/∂t + H(β(x, ∇ₓS(t, x))),    S = Σ_{k≤m} t^k S_k[H_d] + t^M · s_out · N,

with M = 1 by default: H − H_d already enters S at t¹ (S_1 = −H), which a network term of power
t² or more could not correct. s_out is the RMS of H − H_d over the box, the first thing the
network stands for.

The model file is the polynomial realization's (:func:`.polynomial_hj.model_bytes`): its
``system`` is the surrogate system (bracket and H_d, which the loader checks the Taylor table
against), and the training record holds the expression and the surrogate's errors; the core
steps it as any learned polynomial-realization model (no H is needed to step).

Nothing here names a structure: the bracket is the structure's ``bracket_terms()`` (any polynomial
bracket); a structure whose bracket is not polynomial is refused naming ``system``.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..expressions import Expression, default_names
from ..fit import is_int
from ..hamiltonian_family import monomial_exponents, polynomial_text
from ..structures.polynomial import PolynomialBivector, PolynomialPoissonSystem
from .pinn import PinnResult
from .polynomial_hj import (
    PolynomialRealizationGenerating,
    PolynomialTrainConfig,
    build_model,
    hj_derivatives,
    realization_tables,
    train_polynomial,
)

__all__ = [
    "MAX_SURROGATE_DEGREE",
    "SURROGATE_POINTS",
    "ExpressionTrainConfig",
    "Surrogate",
    "expression_residual",
    "fit_surrogate",
    "polynomial_bracket",
    "train_expression",
]

#: Highest degree of the surrogate polynomial (its Taylor-HJ terms grow fast with the degree).
MAX_SURROGATE_DEGREE = 6
#: Seeded uniform points in the box the surrogate is fitted on (and its errors measured on).
SURROGATE_POINTS = 20_000
#: Seed of those points.
SURROGATE_SEED = 7


def polynomial_bracket(system: Any) -> PolynomialBivector:
    """The bracket of ``system`` (its ``bracket_terms()``) as a :class:`PolynomialBivector`.
    ValueError naming 'system' where the bracket is not given as polynomials."""
    import sympy

    try:
        terms = system.bracket_terms()
    except (AttributeError, NotImplementedError) as err:
        raise ValueError(f"system: {err}") from None
    dim = int(system.dim)
    x = sympy.symbols(f"x1:{dim + 1}", real=True)
    pairs = list(itertools.combinations(range(dim), 2))
    entries: dict[tuple[int, int], Any] = {}
    for k, c, e in zip(terms.index, terms.coeffs, terms.exponents, strict=True):
        monomial = sympy.Mul(*(xi ** int(p) for xi, p in zip(x, e, strict=True)))
        pair = pairs[int(k)]
        entries[pair] = entries.get(pair, 0) + sympy.Float(float(c)) * monomial
    return PolynomialBivector(dim, entries)


@dataclass(frozen=True)
class Surrogate:
    """H_d: ``text`` (a polynomial in x1 … xn), its ``degree``, and its errors against H over
    the box (``rms``, ``max``; units of energy)."""

    text: str
    degree: int
    rms: float
    max: float


def _box_samples(x_min: Any, x_max: Any) -> np.ndarray:
    lo, hi = np.asarray(x_min, np.float64), np.asarray(x_max, np.float64)
    rng = np.random.default_rng(SURROGATE_SEED)
    return lo + (hi - lo) * rng.random((SURROGATE_POINTS, lo.size))


def fit_surrogate(expression: Expression, degree: int, x_min: Any, x_max: Any) -> Surrogate:
    """The least-squares polynomial of total degree ≤ ``degree`` to ``expression`` on
    :data:`SURROGATE_POINTS` seeded uniform points of the box [x_min, x_max] (columns scaled to
    unit norm). Terms whose share of H is below the misfit are dropped and the rest refitted
    (twice). ValueError where H is not finite on the box."""
    x = _box_samples(x_min, x_max)
    with np.errstate(all="ignore"):  # a non-finite value is refused just below
        values = np.asarray(expression.evaluate(x), dtype=np.float64)
    if not np.isfinite(values).all():
        raise ValueError(
            f"expression {expression.text[:60]!r} is not finite everywhere on the box "
            f"[{list(x_min)}, {list(x_max)}]: no surrogate"
        )
    exps = [(0,) * x.shape[1], *monomial_exponents(x.shape[1], degree)]
    cols = np.stack([np.prod(x ** np.asarray(e), 1) for e in exps], 1)
    norms = np.linalg.norm(cols, axis=0)

    def fitted(keep: np.ndarray) -> np.ndarray:
        coef = np.zeros(len(exps))
        coef[keep] = np.linalg.lstsq(cols[:, keep] / norms[keep], values, rcond=None)[0]
        return coef / norms

    keep = np.ones(len(exps), dtype=bool)
    for _ in range(2):
        # A term whose part of H is below the fit's own misfit is fitting that misfit: it is
        # dropped and the rest refitted, so that H_d is as sparse as H allows (the cost of its
        # Taylor-HJ terms grows with its terms).
        coef = fitted(keep)
        misfit = np.sqrt(np.mean((cols @ coef - values) ** 2))
        keep &= np.abs(coef) * norms / np.sqrt(len(values)) > misfit
    coef = fitted(keep)
    miss = cols @ coef - values
    terms = {e: float(c) for e, c, k in zip(exps, coef, keep, strict=True) if k}
    return Surrogate(
        text=polynomial_text(terms, default_names(x.shape[1])),
        degree=int(degree),
        rms=float(np.sqrt(np.mean(miss**2))),
        max=float(np.abs(miss).max()),
    )


@dataclass
class ExpressionTrainConfig(PolynomialTrainConfig):
    """A learned S for the expression H ``expression`` on the order-n realization of a
    polynomial bracket: :class:`.polynomial_hj.PolynomialTrainConfig` whose ``system`` is the
    surrogate system (the bracket with H_d), plus the expression and the surrogate's degree.
    Build it with :meth:`of`. Defaults: Taylor order m = 1 on H_d (a dense surrogate makes
    higher terms dear), the network at t¹ (``mlp_power`` 1)."""

    expression: str = ""
    """The true H (the grammar of :mod:`poisson_rs.expressions`) in ``names`` or x1 … xn."""
    names: tuple[str, ...] = ()
    """The coordinates' names the expression may use besides x1 … xn."""
    surrogate_degree: int = 4
    """d: the degree of the least-squares surrogate H_d the Taylor part is built on."""

    @classmethod
    def of(
        cls,
        system: Any,
        *,
        x_min: Any,
        x_max: Any,
        surrogate_degree: int = 4,
        taylor_order: int = 1,
        mlp_power: int | None = 1,
        **options: Any,
    ) -> ExpressionTrainConfig:
        """The configuration for ``system``: an expression system (``h`` an
        :class:`~poisson_rs.expressions.Expression`, a polynomial bracket) on the box
        [x_min, x_max] (each ``system.dim`` finite numbers). ``options``: any other field of
        :class:`.polynomial_hj.PolynomialTrainConfig` (widths, h_max, iterations, ...).
        ValueError naming the field for a bad one."""
        expression = getattr(system, "h", None)
        if not isinstance(expression, Expression):
            raise ValueError(
                "ExpressionTrainConfig field system: needs a system whose H is an expression "
                f"(pr.with_hamiltonian), got {type(system).__name__}"
            )
        if not is_int(surrogate_degree) or not 1 <= surrogate_degree <= MAX_SURROGATE_DEGREE:
            raise ValueError(
                f"ExpressionTrainConfig field surrogate_degree: {surrogate_degree!r} must be an "
                f"integer in [1, {MAX_SURROGATE_DEGREE}]"
            )
        bracket = polynomial_bracket(system)
        lo, hi = (_box(v, name, bracket.dim) for v, name in ((x_min, "x_min"), (x_max, "x_max")))
        if not all(a < b for a, b in zip(lo, hi, strict=True)):
            raise ValueError(
                f"ExpressionTrainConfig field x_max: need x_min < x_max, got {lo}, {hi}"
            )
        surrogate = fit_surrogate(expression, surrogate_degree, lo, hi)
        cfg = cls(
            system=PolynomialPoissonSystem(bracket, surrogate.text),
            x_min=lo,
            x_max=hi,
            taylor_order=taylor_order,
            mlp_power=mlp_power,
            expression=expression.text,
            names=expression.names,
            surrogate_degree=surrogate_degree,
            **options,
        )
        cfg.validate()
        return cfg

    def __post_init__(self) -> None:
        super().__post_init__()
        if isinstance(self.names, list):
            self.names = tuple(self.names)

    def hamiltonian(self) -> Expression:
        """The true H (ValueError naming 'expression' for a text outside the grammar)."""
        dim = self.poisson_system().dim
        names = self.names or default_names(dim)
        if len(names) != dim or not all(isinstance(v, str) for v in names):
            raise ValueError(
                f"ExpressionTrainConfig field names: {self.names!r} must be {dim} strings"
            )
        try:
            return Expression(self.expression, names, aliases=default_names(dim))
        except ValueError as err:
            raise ValueError(f"ExpressionTrainConfig field expression: {err}") from None

    def surrogate(self) -> Surrogate:
        """H_d refitted from the configuration (the same seeded points: the same polynomial)."""
        return fit_surrogate(self.hamiltonian(), self.surrogate_degree, self.x_min, self.x_max)

    def validate(self) -> None:
        super().validate()
        if not is_int(self.surrogate_degree) or not (
            1 <= self.surrogate_degree <= MAX_SURROGATE_DEGREE
        ):
            raise ValueError(
                f"ExpressionTrainConfig field surrogate_degree: {self.surrogate_degree!r} must "
                f"be an integer in [1, {MAX_SURROGATE_DEGREE}]"
            )
        self.hamiltonian()

    def run_training(self, **options: Any) -> Any:
        """Trains this configuration: :func:`train_expression`."""
        return train_expression(self, **options)


def _box(v: Any, name: str, dim: int) -> tuple[float, ...]:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        a = np.empty(0)
    if a.shape != (dim,) or not np.isfinite(a).all():
        raise ValueError(f"ExpressionTrainConfig field {name}: {v!r} must be {dim} finite numbers")
    return tuple(float(c) for c in a)


def expression_residual(
    s_fn: PolynomialRealizationGenerating,
    hamiltonian: Expression,
    t: Tensor,
    x: Tensor,
    create_graph: bool = False,
) -> Tensor:
    """r(t, x) = ∂S/∂t + H(β(x, ∇ₓS)) with H the expression. t (B,), x (B, n) → (B,)."""
    st, sx = hj_derivatives(s_fn, t, x, create_graph)
    with torch.set_grad_enabled(create_graph):
        beta = s_fn.beta(torch.cat([sx, x.detach()], 1))
        return st + hamiltonian.evaluate(beta, torch)


def train_expression(
    cfg: ExpressionTrainConfig,
    *,
    progress: bool = True,
    log_every: int = 10,
    callback: Callable[[int, float], None] | None = None,
    max_seconds: float | None = None,
) -> PinnResult:
    """Trains S = Taylor terms of H_d + t^M · s_out · N on the mean squared HJ residual of the
    true H (:func:`~poisson_rs.realizations.pinn.fit`: Adam, then ``lbfgs_iterations`` of
    L-BFGS); the baseline residual reported is the Taylor part's, against the true H."""
    cfg.validate()
    hamiltonian = cfg.hamiltonian()
    m, n = cfg.taylor_order, cfg.resolved_realization_order()
    tables = realization_tables(cfg.poisson_system(), m, n)
    s_fn = build_model(cfg, tables)
    if s_fn.mlp_power == 1:
        # The network's first job is H − H_d (at t¹): its output is scaled by that RMS.
        s_fn.output_scale = cfg.surrogate().rms or s_fn.output_scale

    def residual(
        model: PolynomialRealizationGenerating, t: Tensor, x: Tensor, create_graph: bool
    ) -> Tensor:
        return expression_residual(model, hamiltonian, t, x, create_graph=create_graph)

    return train_polynomial(
        cfg,
        progress=progress,
        log_every=log_every,
        callback=callback,
        max_seconds=max_seconds,
        model=s_fn,
        residual=residual,
    )
