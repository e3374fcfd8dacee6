"""Symplectic realizations (α, β) of Poisson structures beyond g*, and their generating
functions: the exact log-canonical groupoid (:mod:`.log_canonical`)."""

from .log_canonical import alpha, alpha_log, beta, beta_log, taylor_arrays, taylor_terms

__all__ = ["alpha", "alpha_log", "beta", "beta_log", "taylor_arrays", "taylor_terms"]
