"""Poisson structures and the systems built on them, one module each:

- :mod:`.lie_poisson`: Lie–Poisson systems on g* (a Lie algebra by its structure constants, a
  polynomial Hamiltonian; the rigid body and the heavy top);
- :mod:`.log_canonical`: log-canonical structures π_ij = c_ij x_i x_j with log-polynomial
  Hamiltonians (Lotka–Volterra);
- :mod:`.affine`: affine brackets (Lie–Poisson plus a constant 2-cocycle), through their central
  extension at level 1;
- :mod:`.polynomial`: any polynomial bivector (checked for Jacobi) with its approximate
  realizations of order n.
"""

from .affine import (
    AffineIntegrator,
    AffinePoissonSystem,
    affine_classical,
    affine_learned,
    affine_poisson_system,
    affine_taylor,
    central_extension,
)
from .lie_poisson import HeavyTop, LieAlgebra, LiePoissonSystem, Polynomial, RigidBody
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
    "HeavyTop",
    "LieAlgebra",
    "LiePoissonSystem",
    "LogCanonical",
    "LogCanonicalSystem",
    "LogPolynomial",
    "Polynomial",
    "PolynomialBivector",
    "PolynomialPoissonSystem",
    "RealizationTaylorIntegrator",
    "RigidBody",
    "affine_classical",
    "affine_learned",
    "affine_poisson_system",
    "affine_taylor",
    "central_extension",
    "integer_null_space",
    "lotka_volterra",
]
