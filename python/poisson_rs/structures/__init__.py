"""Poisson structures beyond g* and the systems built on them: log-canonical structures
π_ij = c_ij x_i x_j with log-polynomial Hamiltonians (Lotka–Volterra)."""

from .log_canonical import (
    LogCanonical,
    LogCanonicalSystem,
    LogPolynomial,
    integer_null_space,
    lotka_volterra,
)

__all__ = [
    "LogCanonical",
    "LogCanonicalSystem",
    "LogPolynomial",
    "integer_null_space",
    "lotka_volterra",
]
