"""The log-canonical family's steppers: Taylor-HJ on the exact groupoid in q = ln x, and the
classical baselines (RK4, the midpoint rule, the log splittings, DOP853)."""

from __future__ import annotations

import numbers
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import _core
from ..protocols import (
    NEWTON_MAX_ITER,
    NEWTON_TOL,
    provides,
)

if TYPE_CHECKING:
    pass
from ..rollout import (
    dop853_rollout,
)
from ..structures.log_canonical import LOG_CANONICAL_METHODS


def _log_system(system: Any) -> Any:
    from ..structures.log_canonical import LogCanonicalSystem

    if not isinstance(system, LogCanonicalSystem):
        raise TypeError(f"system must be a LogCanonicalSystem, got {type(system).__name__}")
    return system


def _positive_log(x0: np.ndarray) -> np.ndarray:
    """q0 = ln x0, ValueError naming the first state outside the open positive orthant."""
    bad = ~(x0 > 0).all(axis=1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"mu0 must lie in the open positive orthant (every x_i > 0): state {k} is "
            f"{x0[k].tolist()}"
        )
    # By libm in the core: NumPy's log and exp dispatch on the CPU (AVX-512 kernels where there
    # are some) and differ from libm in the last bit on some arguments, so rollouts converted by
    # them would change bits from one machine to the next.
    q0 = np.array(x0, dtype=np.float64, order="C")
    _core.log_in_place(q0)
    return q0


def _exp_states(traj: np.ndarray) -> np.ndarray:
    """x = e^q of a rollout in q (converted in place when it is a C-contiguous float64 array of
    its own; overflow gives inf, as NumPy's)."""
    out = np.require(traj, dtype=np.float64, requirements=["C", "W"])
    _core.exp_in_place(out)
    return out


@provides("log_canonical.taylor")
class LogCanonicalTaylorIntegrator:
    """Taylor-HJ bisection integrator of a log-canonical system on its exact groupoid.

    S = Σ_{k≤order} t^k S_k with the S_k exact polynomials in y = e^q
    (:func:`poisson_rs.realizations.log_canonical.taylor_terms`); a step solves
    q + ½ c ∇S(q) = ln x_k by Newton in Rust and returns x_{k+1} = exp(q − ½ c ∇S(q)). Every
    monomial Casimir Σ k_i ln x_i is kept to round-off whatever the order. States are x > 0.
    Built by :func:`log_canonical_taylor`.
    """

    system: Any
    order: int
    tol: float
    max_iter: int
    name: str
    _arrays: Any

    def __init__(
        self,
        system: Any,
        order: int = 3,
        *,
        tol: float = NEWTON_TOL,
        max_iter: int = NEWTON_MAX_ITER,
    ):
        from ..realizations.log_canonical import taylor_arrays

        self.system = _log_system(system)
        if isinstance(order, bool) or not isinstance(order, numbers.Integral) or order < 1:
            raise ValueError(f"order must be an integer >= 1, got {order!r}")
        if not (isinstance(tol, numbers.Real) and 0 < tol < 1):
            raise ValueError(f"tol must lie in (0, 1), got {tol!r}")
        if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
            raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")
        self.order = int(order)
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self.name = f"taylor{self.order}-log"
        self._arrays = taylor_arrays(self.system, self.order)

    @property
    def dim(self) -> int:
        return int(self.system.dim)

    @property
    def n_terms(self) -> int:
        """Monomials of S (the log part t·b·q not counted)."""
        return int(self._arrays[2].size)

    def torch_step(self, mu: Any, h: float) -> Any:
        """One step in torch on mu's device (float64): Newton for q + ½ c ∇S(q) = ln x per state,
        stopping as the core does in q = ln x (|δ|∞ ≤ tol · max(|q|∞, 1)), then x' = exp(q − ½ c
        ∇S(q)); a state that does not converge in ``max_iter`` updates comes back NaN.
        mu: (B, n) → (B, n)."""
        import torch

        x = torch.as_tensor(mu, dtype=torch.float64)
        f64, dev = torch.float64, x.device
        # S's tables at t = h on the device, built once per (device, h), not at every step.
        cache = self.__dict__.setdefault("_torch_tables", {})
        if (dev, float(h)) not in cache:
            t_powers, exponents, coeffs = self._arrays
            w = coeffs * float(h) ** t_powers.astype(np.float64)
            cache[dev, float(h)] = (
                torch.tensor(exponents, dtype=f64, device=dev),
                torch.tensor(w, dtype=f64, device=dev),
                torch.tensor(self.system.log_hamiltonian.b, dtype=f64, device=dev) * float(h),
                0.5 * torch.tensor(self.system.c, dtype=f64, device=dev),
            )
        ex, w0, b, half_c = cache[dev, float(h)]

        def derivatives(z: Any) -> tuple[Any, Any]:
            w = w0 * torch.exp(z @ ex.T)  # (B, M)
            return w @ ex + b, torch.einsum("bm,mi,mj->bij", w, ex, ex)

        target = torch.log(x)
        z = target.clone()
        done = torch.zeros(len(z), dtype=torch.bool, device=x.device)
        eye = torch.eye(self.dim, dtype=f64, device=dev)
        for _ in range(self.max_iter):
            g, hs = derivatives(z)
            f = z + g @ half_c.T - target
            delta = torch.linalg.solve(eye + half_c @ hs, -f[..., None])[..., 0]
            delta = torch.where(done[:, None], 0.0, delta)
            z = z + delta
            done |= delta.abs().amax(-1) <= self.tol * z.abs().amax(-1).clamp_min(1.0)
            if bool(done.all()):
                break
        g, _ = derivatives(z)
        return torch.where(done[:, None], torch.exp(z - g @ half_c.T), torch.nan)

    def __reduce__(self) -> tuple[Any, ...]:
        return (
            _restore_log_taylor,
            (type(self), self.system.to_dict(), self.order, self.tol, self.max_iter),
        )

    def rollout(
        self, mu0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        t_powers, exponents, coeffs = self._arrays
        # At the fixed t = h, terms with the same y-exponent merge into one (S₁, S₃, S₅ share
        # most monomials): fewer terms for every Newton update.
        exponents, inverse = np.unique(exponents, axis=0, return_inverse=True)
        merged = np.zeros(len(exponents))
        np.add.at(merged, inverse.ravel(), coeffs * h ** t_powers.astype(np.float64))
        q, info = _core.rollout_log_canonical(
            np.ascontiguousarray(self.system.c),
            np.zeros(len(merged), dtype=np.int64),
            np.ascontiguousarray(exponents, dtype=np.int64),
            merged,
            np.ascontiguousarray(self.system.log_hamiltonian.b),
            _positive_log(mu0),
            h,
            n_steps,
            every,
            self.tol,
            self.max_iter,
        )
        return _exp_states(q), info

    def __repr__(self) -> str:
        return f"{type(self).__name__}(order={self.order}, system={self.system!r})"


def _restore_log_taylor(
    cls: type[LogCanonicalTaylorIntegrator], data: Any, order: int, tol: float, max_iter: int
) -> LogCanonicalTaylorIntegrator:
    from ..structures.log_canonical import LogCanonicalSystem

    return cls(LogCanonicalSystem.from_dict(data), order, tol=tol, max_iter=max_iter)


@provides("log_canonical.classical")
class LogCanonicalClassicalIntegrator:
    """A classical baseline for a log-canonical system, driven by :func:`integrate`.

    - "rk4", "midpoint": explicit RK4 and the implicit midpoint rule (Newton, exact Jacobian) in
      x, in Rust; neither is Poisson, and a step that leaves the positive orthant fails (code 5).
    - "log_splitting", "log_splitting4": in q = ln x, H = Σ_i H_i(q_i) splits into one-variable
      terms with exact explicit flows q_j += t c_ji H_i'(q_i); Strang's composition (order 2)
      and Suzuki's 5-stage composition of it (order 4), in Rust. Poisson maps: every monomial
      Casimir is kept to round-off. Need a separable H (Lotka–Volterra is).
    - "dop853": SciPy's adaptive DOP853 in q with rtol = atol = ``tol`` (h only spaces output).
    """

    system: Any
    name: str
    tol: float
    max_iter: int

    def __init__(
        self, system: Any, name: str, *, tol: float = NEWTON_TOL, max_iter: int = NEWTON_MAX_ITER
    ):
        self.system = _log_system(system)
        if not (isinstance(name, str) and name in LOG_CANONICAL_METHODS):
            raise ValueError(
                f"unknown classical integrator {name!r} for a log-canonical system; valid "
                f"names: {', '.join(LOG_CANONICAL_METHODS)}"
            )
        if not (isinstance(tol, numbers.Real) and 0 < tol < 1):
            raise ValueError(f"tol must lie in (0, 1), got {tol!r}")
        if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
            raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")
        self.name = name
        self.tol = float(tol)
        self.max_iter = int(max_iter)

    @property
    def dim(self) -> int:
        return int(self.system.dim)

    @property
    def order(self) -> int:
        return LOG_CANONICAL_METHODS[self.name][0]

    @property
    def poisson(self) -> bool:
        return LOG_CANONICAL_METHODS[self.name][1]

    @property
    def torch_graph(self) -> bool:
        """Whether :meth:`torch_step` is one graph (no data-dependent control flow), which
        ``torch.compile`` fuses on a device: RK4's is."""
        return self.name == "rk4"

    def torch_step(self, mu: Any, h: float) -> Any:
        """One RK4 step in x in torch on mu's device and dtype (the device rollouts'
        :func:`~poisson_rs.on_device`; a state leaving the orthant turns NaN). mu: (B, n) → (B, n).
        """
        import torch

        from .classical_torch import require_torch_method, rk4_step

        require_torch_method(self.name, "the classical integrator")
        system = self.system

        def field(x: Any) -> Any:
            # ẋ = x ∘ (c ∇_q H(ln x)) without the positivity check of ``vector_field`` (a host
            # sync): a stage outside the orthant gives NaN, and the step fails there.
            return x * system.vector_field_log(torch.log(x))

        out = rk4_step(field, mu, float(h))
        return torch.where((out > 0).all(-1, keepdim=True), out, torch.nan)

    def __reduce__(self) -> tuple[Any, ...]:
        return (
            _restore_log_classical,
            (type(self), self.system.to_dict(), self.name, self.tol, self.max_iter),
        )

    def rollout(
        self, mu0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        q0 = _positive_log(mu0)
        if self.name == "dop853":
            return dop853_rollout(self.system, mu0, h, n_steps, every, self.tol)
        powers, coeffs, b = self.system.log_hamiltonian.to_arrays()
        in_log = self.name.startswith("log_")
        traj, info = _core.rollout_log_classical(
            self.name,
            np.ascontiguousarray(self.system.c),
            powers,
            coeffs,
            b,
            q0 if in_log else mu0,
            h,
            n_steps,
            every,
            self.tol,
            self.max_iter,
        )
        return (_exp_states(traj) if in_log else traj), info

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, system={self.system!r})"


def _restore_log_classical(
    cls: type[LogCanonicalClassicalIntegrator], data: Any, name: str, tol: float, max_iter: int
) -> LogCanonicalClassicalIntegrator:
    from ..structures.log_canonical import LogCanonicalSystem

    return cls(LogCanonicalSystem.from_dict(data), name, tol=tol, max_iter=max_iter)
