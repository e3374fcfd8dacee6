"""Poisson structures beyond g* and the systems built on them: log-canonical structures
π_ij = c_ij x_i x_j with log-polynomial Hamiltonians (Lotka–Volterra), and any polynomial
bivector (checked for Jacobi) with its approximate realizations of order n, and affine brackets
(Lie–Poisson plus a constant 2-cocycle) through their central extension at level 1."""

from .affine import (
    AffineIntegrator,
    AffinePoissonSystem,
    affine_classical,
    affine_learned,
    affine_poisson_system,
    affine_taylor,
    central_extension,
)
from .log_canonical import (
    LogCanonical,
    LogCanonicalSystem,
    LogPolynomial,
    integer_null_space,
    lotka_volterra,
)
from .polynomial import PolynomialBivector, PolynomialPoissonSystem, RealizationTaylorIntegrator

__all__ = [
    "AffineIntegrator",
    "AffinePoissonSystem",
    "LogCanonical",
    "LogCanonicalSystem",
    "LogPolynomial",
    "PolynomialBivector",
    "PolynomialPoissonSystem",
    "RealizationTaylorIntegrator",
    "affine_classical",
    "affine_learned",
    "affine_poisson_system",
    "affine_taylor",
    "central_extension",
    "integer_null_space",
    "lotka_volterra",
]
