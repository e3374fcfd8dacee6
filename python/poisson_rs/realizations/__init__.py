"""Symplectic realizations (α, β) of Poisson structures, and their generating functions:

- :mod:`.lie_groupoid`: the exact groupoid T*G ⇉ g* of a Lie algebra in its charts (NumPy and
  torch);
- :mod:`.log_canonical`: the exact log-canonical groupoid and its Hamilton–Jacobi series;
- :mod:`.log_canonical_hj`, :mod:`.polynomial_hj`: the learned S on the log-canonical groupoid
  and on the order-n realization of a polynomial bivector (:mod:`.pinn` holds what they share);
- :mod:`.expression_hj`: the learned S for an expression H on that realization (Taylor terms of a
  polynomial surrogate of H, the network trained on the true H's residual).

The order-n realizations themselves are built with their bivector
(:meth:`poisson_rs.structures.polynomial.PolynomialBivector.realization`).
"""

from .log_canonical import alpha, alpha_log, beta, beta_log, taylor_arrays, taylor_terms

__all__ = ["alpha", "alpha_log", "beta", "beta_log", "taylor_arrays", "taylor_terms"]
