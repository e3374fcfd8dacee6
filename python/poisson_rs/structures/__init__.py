"""Poisson structures beyond g* and the systems built on them: log-canonical structures
π_ij = c_ij x_i x_j with log-polynomial Hamiltonians (Lotka–Volterra), and any polynomial
bivector (checked for Jacobi) with its order-2 approximate realization."""

from .log_canonical import (
    LogCanonical,
    LogCanonicalSystem,
    LogPolynomial,
    integer_null_space,
    lotka_volterra,
)
from .polynomial import PolynomialBivector, PolynomialPoissonSystem, RealizationTaylorIntegrator

__all__ = [
    "LogCanonical",
    "LogCanonicalSystem",
    "LogPolynomial",
    "PolynomialBivector",
    "PolynomialPoissonSystem",
    "RealizationTaylorIntegrator",
    "integer_null_space",
    "lotka_volterra",
]
