"""Learned generating functions (the PINN) on the exact log-canonical groupoid.

In q = ln x the groupoid of π_ij = c_ij x_i x_j is T*Rⁿ with base q, fibre P, and linear maps
β(q, P) = q − ½ c P (source, Poisson) and α(q, P) = q + ½ c P (target, anti-Poisson); see
:mod:`poisson_rs.realizations.log_canonical`. A generating function S(t, q) gives the
Lagrangian bisection P = ∇_q S(t, q); a step of size h from q_k solves α(q, ∇S(h, q)) = q_k for
q and returns q_{k+1} = β(q, ∇S(h, q)). The step is a Poisson map and keeps every monomial
Casimir Σ k_i q_i (c k = 0) exactly, whatever S is: k·β = k·q − ½ (cᵀk)·P = k·q = k·α.

The step is the time-h flow when S solves the Hamilton–Jacobi equation of this realization

    r(t, q) = ∂S/∂t(t, q) + H(β(q, ∇_q S(t, q))) = 0,   S(0, ·) = 0,

with H(q) = Σ_m a_m e^{e_m·q} − b·q the Hamiltonian in log coordinates (units of energy; t in
time units). Its Taylor series S = Σ_k t^k S_k is exact up to a chosen order K
(:func:`~poisson_rs.realizations.log_canonical.taylor_terms`; S_k = 0 for even k on
Lotka–Volterra), and truncating it leaves r = O(t^{K+1}) (tested with a fitted slope).

The learned model follows the Lie–Poisson design (:mod:`poisson_rs.train`):

    S(t, q) = Σ_{k≤K} t^k S_k(q) + t^m · s_out · N(t/h_max, (q − q_c)/q_w),

N a small tanh MLP whose last layer starts at zero (so training starts at the Taylor terms),
m = K + 2 where S_{K+1} vanishes (K + 1 otherwise), trained by Adam (then optionally L-BFGS) on
the mean squared residual r over t ∈ [0, h_max] and q uniform in a box of log coordinates. The
exported file carries the scales folded into the first and last layers, so the Rust core sees
S = Taylor + t^m N(t, q) (``_core.LearnedModel``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..fit import FitConfig, is_int
from ..structures.log_canonical import LogCanonicalSystem
from .log_canonical import beta_log, taylor_arrays
from .pinn import NetworkTerm, PinnResult, box_points, fit, model_file, provenance

#: The ``structure`` metadata of a log-canonical model file.
STRUCTURE = "log_canonical"


def _system_of(spec: dict[str, Any] | LogCanonicalSystem) -> LogCanonicalSystem:
    if isinstance(spec, LogCanonicalSystem):
        return spec
    if not isinstance(spec, Mapping):
        raise TypeError(
            f"system must be a LogCanonicalSystem or its to_dict(), got {type(spec).__name__}"
        )
    return LogCanonicalSystem.from_dict(spec)


def _taylor_vanishes(system: LogCanonicalSystem, order: int) -> bool:
    """Whether S_order is identically zero (even orders on Lotka–Volterra)."""
    tp, _, co = taylor_arrays(system, order)
    return not bool(np.any(co[tp == order] != 0))


class LogCanonicalGenerating(NetworkTerm):
    """S(t, q) = Σ coeffs · t^k e^{e·q} + t·(b·q) + t^m · s_out · N(t·s_t, (q − q_c)·s_q).

    ``system``: the log-canonical system; ``taylor_order`` K ≥ 1 (exact terms S_1..S_K, S_1 with
    its log part +t b·q); ``widths`` the hidden widths of N (empty: no network);
    ``mlp_power`` m ≥ 1; ``q_center``, ``q_half`` (n,) the box of log coordinates the inputs are
    scaled from; ``h_max`` the time scale; ``output_scale`` s_out. Evaluated on t (B,),
    q (B, n) → (B,).
    """

    # Buffers, declared so that they type as tensors (not ``nn.Module.__getattr__``'s union).
    t_powers: Tensor
    exponents: Tensor
    coeffs: Tensor
    linear: Tensor

    def __init__(
        self,
        system: LogCanonicalSystem,
        taylor_order: int,
        widths: tuple[int, ...],
        mlp_power: int,
        q_center: np.ndarray,
        q_half: np.ndarray,
        h_max: float,
        output_scale: float = 1.0,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__(system.dim, widths, q_center, q_half, h_max, output_scale, dtype)
        self.mlp_power = int(mlp_power)
        self.taylor_order = int(taylor_order)
        tp, ex, co = taylor_arrays(system, taylor_order)
        self.register_buffer("t_powers", torch.as_tensor(tp, dtype=dtype))
        self.register_buffer("exponents", torch.as_tensor(ex, dtype=dtype))
        self.register_buffer("coeffs", torch.as_tensor(co, dtype=dtype))
        b = np.array(system.log_hamiltonian.b, dtype=np.float64)
        self.register_buffer("linear", torch.tensor(b, dtype=dtype))
        self._powers_int = np.concatenate([tp[:, None], ex], axis=1).astype(np.int64)
        self._coeffs64 = co.astype(np.float64)
        self._linear64 = np.array(system.log_hamiltonian.b, dtype=np.float64)

    def taylor(self, t: Tensor, q: Tensor) -> Tensor:
        """The exact Taylor terms Σ_{k≤K} t^k S_k(q) (S_1's log part included): (B,)."""
        w = self.coeffs * t[:, None] ** self.t_powers * torch.exp(q @ self.exponents.T)
        return w.sum(-1) + t * (q @ self.linear)

    def forward(self, t: Tensor, q: Tensor) -> Tensor:
        s = self.taylor(t, q)
        if len(self.linears):
            s = s + t**self.mlp_power * self.output_scale * self.network(t, q)
        return s

    def taylor_tensors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(powers int64 (M, 1 + n) rows (k, e), coeffs (M,), linear (n,)) of the Taylor part."""
        return self._powers_int.copy(), self._coeffs64.copy(), self._linear64.copy()


def hj_derivatives(
    s_fn: torch.nn.Module, t: Tensor, q: Tensor, create_graph: bool
) -> tuple[Tensor, Tensor]:
    """∂S/∂t (B,) and ∇_q S (B, n) by autograd; differentiable in the weights if
    ``create_graph``."""
    t = t.detach().requires_grad_(True)
    q = q.detach().requires_grad_(True)
    with torch.enable_grad():
        s = s_fn(t, q)
        st, sq = torch.autograd.grad(s.sum(), (t, q), create_graph=create_graph)
    return st, sq


def hj_residual(
    s_fn: torch.nn.Module,
    system: LogCanonicalSystem,
    t: Tensor,
    q: Tensor,
    create_graph: bool = False,
) -> Tensor:
    """r(t, q) = ∂S/∂t + H(β(q, ∇_q S)) with β(q, P) = q − ½ c P and H in log coordinates.
    t (B,) time units, q (B, n) = ln x → (B,) units of energy."""
    st, sq = hj_derivatives(s_fn, t, q, create_graph)
    with torch.set_grad_enabled(create_graph):
        return st + system.log_hamiltonian.in_log(beta_log(system.c, q.detach(), sq))


def step_map(
    s_fn: torch.nn.Module,
    system: LogCanonicalSystem,
    q: Tensor,
    h: float,
    tol: float = 1e-13,
    max_iter: int = 50,
) -> Tensor:
    """One step of the bisection integrator of ``s_fn`` in torch (the oracle of the Rust step):
    Newton on q + ½ c ∇S(h, q) = q_k from q = q_k with the autograd Hessian, then
    q_{k+1} = q − ½ c ∇S(h, q). q (B, n) float64 → (B, n); NaN rows where Newton fails."""
    c = torch.tensor(np.array(system.c), dtype=q.dtype)
    n = q.shape[1]
    t = torch.full((q.shape[0],), float(h), dtype=q.dtype)
    z = q.detach().clone()
    converged = torch.zeros(q.shape[0], dtype=torch.bool)
    for _ in range(max_iter):
        zv = z.detach().requires_grad_(True)
        with torch.enable_grad():
            (g,) = torch.autograd.grad(s_fn(t, zv).sum(), zv, create_graph=True)
            hess = torch.stack(
                [torch.autograd.grad(g[:, i].sum(), zv, retain_graph=True)[0] for i in range(n)],
                1,
            )
        g, hess = g.detach(), hess.detach()
        f = z + 0.5 * g @ c.T - q
        jac = torch.eye(n, dtype=q.dtype) + 0.5 * c @ hess
        delta = torch.linalg.solve(jac, -f[..., None])[..., 0]
        z = z + delta
        scale = z.abs().amax(1).clamp_min(1.0)
        converged = delta.abs().amax(1) <= tol * scale
        if bool(converged.all()):
            break
    _, g = hj_derivatives(s_fn, t, z, create_graph=False)
    out = z - 0.5 * g @ c.T
    return torch.where(converged[:, None], out.detach(), torch.full_like(out, float("nan")))


# ---------------------------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------------------------


@dataclass
class LogCanonicalTrainConfig(FitConfig):
    """Everything that determines a training run of a log-canonical generating function (and is
    recorded in the model file). The defaults are sized for PNN's Lotka–Volterra scene
    (states (1, 0.8), (1, 1), (1, 1.2), h = 0.1), whose orbits span u ∈ [0.25, 2.57],
    v ∈ [0.8, 4.04]."""

    system: dict[str, Any] | LogCanonicalSystem
    """The log-canonical system, or its ``to_dict()``; stored as the dictionary (JSON)."""
    taylor_order: int = 3
    """K: exact Taylor terms S_1..S_K in S."""
    mlp_power: int | None = None
    """m in t^m·N; default K + 2 where S_{K+1} vanishes, else K + 1."""
    widths: tuple[int, ...] = (16, 16)
    x_min: tuple[float, ...] = (0.2, 0.6)
    """Lower corner of the training box, in x (positive); q is drawn uniform in [ln x_min,
    ln x_max]."""
    x_max: tuple[float, ...] = (3.2, 5.0)
    h_max: float = 0.1
    batch: int = 1024
    iterations: int = 2000
    lr: float = 3e-3
    schedule: str = "cosine"
    seed: int = 0
    dtype: str = "float64"
    lbfgs_iterations: int = 0
    """L-BFGS iterations (strong-Wolfe line search) after Adam on one fixed seeded batch of
    ``lbfgs_batch`` points; 0: none. On the PNN scene it takes the residual from ~15x to ~900x
    below the Taylor terms' (docs/learned_log_canonical.md)."""
    lbfgs_batch: int = 4096

    def polish_batch(self) -> int:
        return self.lbfgs_batch

    def run_training(self, **options: Any) -> Any:
        """Trains this configuration: :func:`train_log_canonical` (what
        :func:`poisson_rs.train.train` calls for it)."""
        return train_log_canonical(self, **options)

    def __post_init__(self) -> None:
        if isinstance(self.system, LogCanonicalSystem):
            self.system = self.system.to_dict()
        self.widths = tuple(self.widths)
        self.x_min = tuple(self.x_min)
        self.x_max = tuple(self.x_max)

    def log_system(self) -> LogCanonicalSystem:
        try:
            return _system_of(self.system)
        except (TypeError, ValueError) as e:
            raise ValueError(f"LogCanonicalTrainConfig field system: {e}") from None

    def resolved_mlp_power(self) -> int:
        if self.mlp_power is not None:
            return self.mlp_power
        k = self.taylor_order
        return k + 2 if _taylor_vanishes(self.log_system(), k + 1) else k + 1

    def validate(self) -> None:
        """Raises ValueError (TypeError for a wrong type) naming the first bad field."""
        system = self.log_system()
        n = system.dim
        ints = {
            "taylor_order": (self.taylor_order, 1, 9),
            "batch": (self.batch, 1, 10_000_000),
            "iterations": (self.iterations, 0, 10**9),
            "seed": (self.seed, 0, 2**63 - 1),
            "lbfgs_iterations": (self.lbfgs_iterations, 0, 10**7),
            "lbfgs_batch": (self.lbfgs_batch, 1, 10_000_000),
        }
        if self.mlp_power is not None:
            ints["mlp_power"] = (self.mlp_power, 1, 64)
        for name, (v, lo, hi) in ints.items():
            if not is_int(v) or not lo <= v <= hi:
                raise ValueError(f"invalid {name}: {v!r} (must be an integer in [{lo}, {hi}])")
        if not all(is_int(w) and 1 <= w <= 100_000 for w in self.widths):
            raise ValueError(f"invalid widths: {self.widths!r} (integers in [1, 100000])")
        for name, x in (("h_max", self.h_max), ("lr", self.lr)):
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not 0 < x < math.inf:
                raise ValueError(f"invalid {name}: {x!r} (must be a finite number > 0)")
        for name, box in (("x_min", self.x_min), ("x_max", self.x_max)):
            if len(box) != n or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < math.inf
                for v in box
            ):
                raise ValueError(
                    f"invalid {name}: {box!r} (must be {n} finite numbers > 0: the training "
                    "box lies in the open positive orthant)"
                )
        if not all(a < b for a, b in zip(self.x_min, self.x_max, strict=True)):
            raise ValueError(f"invalid x_max: need x_min < x_max, got {self.x_min}, {self.x_max}")
        if self.schedule not in ("cosine", "constant"):
            raise ValueError(f"invalid schedule: {self.schedule!r} ('cosine' or 'constant')")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"invalid dtype: {self.dtype!r} ('float32' or 'float64')")

    def domain_dict(self) -> dict[str, Any]:
        return {
            "kind": "box",
            "x_min": list(self.x_min),
            "x_max": list(self.x_max),
            "t_max": self.h_max,
        }

    def q_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(center, half width) of the box in q = ln x."""
        lo, hi = np.log(np.array(self.x_min)), np.log(np.array(self.x_max))
        return 0.5 * (lo + hi), 0.5 * (hi - lo)


def sample_points(
    cfg: LogCanonicalTrainConfig, n: int, gen: torch.Generator, dtype: torch.dtype
) -> tuple[Tensor, Tensor]:
    """n points: t (n,) uniform in [0, h_max], q (n, dim) uniform in the log box."""
    return box_points(cfg.q_box(), cfg.h_max, n, gen, dtype)


def build_model(cfg: LogCanonicalTrainConfig) -> LogCanonicalGenerating:
    """The untrained model (seeded; last layer zero, so S starts as the Taylor terms). The
    network's output is scaled by the RMS over the box of S_m, the first term it stands in for
    (1 where S_m vanishes)."""
    system = cfg.log_system()
    dtype = getattr(torch, cfg.dtype)
    m = cfg.resolved_mlp_power()
    center, half = cfg.q_box()
    gen = torch.Generator().manual_seed(cfg.seed + 1)
    _, q = sample_points(cfg, 2048, gen, torch.float64)
    tp, ex, co = taylor_arrays(system, m)
    sel = tp == m
    vals = np.exp(q.numpy() @ ex[sel].T) @ co[sel]
    out_scale = float(np.sqrt(np.mean(vals**2))) or 1.0
    torch.manual_seed(cfg.seed)
    s_fn = LogCanonicalGenerating(
        system, cfg.taylor_order, cfg.widths, m, center, half, cfg.h_max, out_scale, dtype
    )
    s_fn.zero_output_layer()
    return s_fn


#: The result of :func:`train_log_canonical`.
LogCanonicalTrainResult = PinnResult


def train_log_canonical(
    cfg: LogCanonicalTrainConfig,
    *,
    progress: bool = True,
    log_every: int = 10,
    callback: Callable[[int, float], None] | None = None,
    max_seconds: float | None = None,
) -> PinnResult:
    """Trains S = Taylor terms + t^m·N on the mean squared HJ residual of the exact groupoid
    (:func:`~poisson_rs.realizations.pinn.fit`: Adam, then ``lbfgs_iterations`` of L-BFGS).
    ``progress`` shows a tqdm bar; ``max_seconds`` ends the run cleanly once that much time has
    passed. Threads are the caller's (``poisson_rs.train.train`` applies the package's
    policy)."""
    cfg.validate()
    system = cfg.log_system()

    def residual(s_fn: torch.nn.Module, t: Tensor, q: Tensor, create_graph: bool) -> Tensor:
        return hj_residual(s_fn, system, t, q, create_graph=create_graph)

    def sample(n: int, gen: torch.Generator, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        return sample_points(cfg, n, gen, dtype)

    return fit(
        cfg,
        build_model(cfg),
        lambda: build_model(dataclasses.replace(cfg, dtype="float64")),
        residual,
        sample,
        progress=progress,
        log_every=log_every,
        callback=callback,
        max_seconds=max_seconds,
    )


# ---------------------------------------------------------------------------------------------
# Model files
# ---------------------------------------------------------------------------------------------


def model_bytes(
    s_fn: LogCanonicalGenerating,
    cfg: LogCanonicalTrainConfig,
    record: Mapping[str, Any] | None = None,
) -> bytes:
    """The model file of ``s_fn`` (safetensors, float64): tensors ``structure.c``,
    ``poly.powers`` (M, 1 + n) rows (k, e) for t^k e^{e·q}, ``poly.coeffs``, ``poly.linear``
    (t·linear·q), ``mlp.{i}.weight``/``.bias`` on raw inputs (t, q); metadata ``format``,
    ``structure = log_canonical``, ``mlp_power``, ``mlp_inputs = t,p``, ``widths``,
    ``taylor_order``, ``system`` (JSON), ``h_max``, ``domain`` (JSON), and ``record`` entries
    (non-strings as JSON). Refuses NaN or infinite weights (a diverged run)."""
    system = cfg.log_system()
    powers, coeffs, linear = s_fn.taylor_tensors()
    tensors: dict[str, np.ndarray] = {
        "structure.c": np.ascontiguousarray(system.c, dtype=np.float64),
        "poly.powers": np.ascontiguousarray(powers, dtype=np.int64),
        "poly.coeffs": np.ascontiguousarray(coeffs, dtype=np.float64),
        "poly.linear": np.ascontiguousarray(linear, dtype=np.float64),
    }
    return model_file(
        tensors, s_fn, cfg, structure=STRUCTURE, system=system, inputs="t,p", record=record
    )


def save_result(
    result: LogCanonicalTrainResult,
    path: str | Path,
    *,
    name: str,
    command: str,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Writes a trained model with its provenance (command, seed, residuals, time) atomically."""
    from ..files import atomic_write_bytes

    record = provenance(result, name=name, command=command, extra=extra)
    return atomic_write_bytes(Path(path), model_bytes(result.model, result.config, record))
