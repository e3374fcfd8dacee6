"""Learned generating functions (the PINN) on the order-n approximate realization of a polynomial
bivector.

The realization (:meth:`poisson_rs.structures.polynomial.PolynomialBivector.realization`) gives
β(x, p) (source, Poisson to O(|p|^n)) and α(x, p) = β(x, −p) (target) as polynomials in the
momenta p and the base point x. A generating function S(t, x) gives the Lagrangian bisection
p = ∇_x S(t, x); a step of size h from x_k solves α(x, ∇S(h, x)) = x_k for x by Newton and
returns x_{k+1} = β(x, ∇S(h, x)). The step is the time-h flow of H∘β on the realization when S
solves the Hamilton–Jacobi equation

    r(t, x) = ∂S/∂t(t, x) + H(β(x, ∇_x S(t, x))) = 0,   S(0, ·) = 0,

(H in units of energy, t in time units). Its Taylor series S = Σ_k t^k S_k
(:func:`~poisson_rs.structures.polynomial.hj_series`) truncated at order m leaves
r = O(t^m), or O(t^{m+1}) where S_{m+1} vanishes (fitted in the tests). Because β is Poisson
only to O(|p|^n), even an exact S inherits the realization's defect: the map keeps the
Casimirs only to O(h^{n+1}) a step (O(h^{n+2}) for odd n), and its order is at most n (n + 1
for odd n: the scheme is symmetric). A network can therefore only buy back what the truncated
Taylor series loses, on a realization of high enough order.

The model follows the log-canonical one (:mod:`poisson_rs.realizations.log_canonical_hj`):

    S(t, x) = Σ_{k≤m} t^k S_k(x) + t^M · s_out · N(t/h_max, (x − x_c)/x_w),

N a small tanh MLP whose last layer starts at zero, M = m + 2 where S_{m+1} vanishes (m + 1
otherwise), trained by Adam (then optionally L-BFGS) on the mean squared residual over
t ∈ [0, h_max] and x uniform in a box. Every polynomial (β, α, S's Taylor terms, H) is carried
as the same term table the Rust core reads, and evaluated in torch by repeated multiplication
(exact derivatives at 0, unlike a float power). The model file holds those tables and the
network with its scales folded in; the core steps it (``_core.LearnedModel``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from torch import Tensor

from ..fit import FitConfig, is_int
from ..structures.polynomial import (
    MAX_REALIZATION_ORDER,
    PolynomialPoissonSystem,
    _term_table,
    hj_series,
    matched_realization_order,
)
from .pinn import NetworkTerm, PinnResult, box_points, fit, model_file, provenance

#: The ``structure`` metadata of a learned polynomial-realization model file.
STRUCTURE = "polynomial"
#: Highest Taylor-HJ order m accepted (that of :class:`RealizationTaylorIntegrator`).
MAX_TAYLOR_ORDER = 5
#: The term tables of a model file: (index, coeffs, exponents) for β and α, (coeffs, exponents)
#: for the Taylor part of S.
TABLE_TENSORS = (
    "sou.index",
    "sou.coeffs",
    "sou.exponents",
    "tar.index",
    "tar.coeffs",
    "tar.exponents",
    "taylor.coeffs",
    "taylor.exponents",
)

Table = tuple[np.ndarray, np.ndarray, np.ndarray]


def _system_of(spec: Mapping[str, Any] | PolynomialPoissonSystem) -> PolynomialPoissonSystem:
    if isinstance(spec, PolynomialPoissonSystem):
        return spec
    if not isinstance(spec, Mapping):
        raise TypeError(
            f"system must be a PolynomialPoissonSystem or its to_dict(), got {type(spec).__name__}"
        )
    return PolynomialPoissonSystem.from_dict(spec)


@dataclass(frozen=True)
class RealizationTables:
    """The polynomials of one (system, m, n) as term tables.

    ``beta``, ``alpha``: (index (K,), coeffs (K,), exponents (K, 2n)) over (p, x), the fibre
    first, as :func:`poisson_rs._core.rollout_polynomial_realization` reads them; ``taylor``:
    (index, coeffs, exponents (K, 1 + n)) of Σ_{k≤m} t^k S_k over (t, x); ``hamiltonian``: H over
    x; ``next_term_vanishes``: whether S_{m+1} = 0."""

    beta: Table
    alpha: Table
    taylor: Table
    hamiltonian: Table
    next_term_vanishes: bool


def realization_tables(
    system: PolynomialPoissonSystem, taylor_order: int, realization_order: int
) -> RealizationTables:
    """Derives the tables with sympy (cached per system and orders by the structure module)."""
    import sympy

    x = system.structure.x
    beta, alpha, p = system.structure.realization(realization_order)
    terms = hj_series(system, taylor_order + 1, realization_order)
    t = sympy.Symbol("t")
    s_full = sum(t**k * s for k, s in enumerate(terms[:taylor_order], start=1))
    return RealizationTables(
        beta=_term_table(beta, (*p, *x)),
        alpha=_term_table(alpha, (*p, *x)),
        taylor=_term_table([s_full], (t, *x)),
        hamiltonian=_term_table([system.h], x),
        next_term_vanishes=sympy.expand(terms[taylor_order]) == 0,
    )


class TermPolynomials(torch.nn.Module):
    """Evaluates a term table in torch: out[:, index[k]] += coeffs[k] · Π_j v_j^exponents[k, j].
    Powers by repeated multiplication, so autograd is exact everywhere (v_j^0 = 1 has zero
    derivative, also at v_j = 0). v (B, V) → (B, n_out)."""

    # Buffers, declared so that they type as tensors (not ``nn.Module.__getattr__``'s union).
    index: Tensor
    coeffs: Tensor
    exponents: Tensor

    def __init__(self, table: Table, n_out: int, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        index, coeffs, exponents = table
        self.n_out = int(n_out)
        self.max_power = int(exponents.max()) if exponents.size else 0
        self.register_buffer("index", torch.as_tensor(index, dtype=torch.int64))
        self.register_buffer("coeffs", torch.as_tensor(coeffs, dtype=dtype))
        self.register_buffer("exponents", torch.as_tensor(exponents, dtype=torch.int64))

    def forward(self, v: Tensor) -> Tensor:
        powers = [torch.ones_like(v)]
        for _ in range(self.max_power):
            powers.append(powers[-1] * v)
        stack = torch.stack(powers, 0)  # (P + 1, B, V)
        cols = torch.arange(v.shape[1])
        # (K, V, B): v_j^{e_kj} for each term k and variable j.
        picked = stack[self.exponents, :, cols[None, :]]
        terms = self.coeffs.to(v.dtype)[:, None] * picked.prod(1)  # (K, B)
        out = torch.zeros(v.shape[0], self.n_out, dtype=v.dtype)
        return out.index_add(1, self.index, terms.T)


class PolynomialRealizationGenerating(NetworkTerm):
    """S(t, x) = Taylor(t, x) + t^M · s_out · N((t, x) scaled), with the maps of the realization.

    ``tables``: the system's :class:`RealizationTables`; ``widths`` the hidden widths of N
    (empty: no network); ``mlp_power`` M ≥ 1; ``x_center``, ``x_half`` (n,) the box the inputs
    are scaled from; ``h_max`` the time scale; ``output_scale`` s_out. Evaluated on t (B,),
    x (B, n) → (B,)."""

    def __init__(
        self,
        tables: RealizationTables,
        dim: int,
        taylor_order: int,
        realization_order: int,
        widths: tuple[int, ...],
        mlp_power: int,
        x_center: np.ndarray,
        x_half: np.ndarray,
        h_max: float,
        output_scale: float = 1.0,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__(dim, widths, x_center, x_half, h_max, output_scale, dtype)
        self.tables = tables
        self.taylor_order = int(taylor_order)
        self.realization_order = int(realization_order)
        self.mlp_power = int(mlp_power)
        self.beta = TermPolynomials(tables.beta, dim, dtype)
        self.alpha = TermPolynomials(tables.alpha, dim, dtype)
        self.taylor_part = TermPolynomials(tables.taylor, 1, dtype)
        self.hamiltonian = TermPolynomials(tables.hamiltonian, 1, dtype)

    def taylor(self, t: Tensor, x: Tensor) -> Tensor:
        """Σ_{k≤m} t^k S_k(x): (B,)."""
        return self.taylor_part(torch.cat([t[:, None], x], 1))[:, 0]

    def forward(self, t: Tensor, x: Tensor) -> Tensor:
        s = self.taylor(t, x)
        if len(self.linears):
            s = s + t**self.mlp_power * self.output_scale * self.network(t, x)
        return s


def hj_derivatives(
    s_fn: torch.nn.Module, t: Tensor, x: Tensor, create_graph: bool
) -> tuple[Tensor, Tensor]:
    """∂S/∂t (B,) and ∇_x S (B, n) by autograd; differentiable in the weights if
    ``create_graph``."""
    t = t.detach().requires_grad_(True)
    x = x.detach().requires_grad_(True)
    with torch.enable_grad():
        s = s_fn(t, x)
        st, sx = torch.autograd.grad(s.sum(), (t, x), create_graph=create_graph)
    return st, sx


def hj_residual(
    s_fn: PolynomialRealizationGenerating, t: Tensor, x: Tensor, create_graph: bool = False
) -> Tensor:
    """r(t, x) = ∂S/∂t + H(β(x, ∇_x S)). t (B,) time units, x (B, n) → (B,) units of energy."""
    st, sx = hj_derivatives(s_fn, t, x, create_graph)
    with torch.set_grad_enabled(create_graph):
        beta = s_fn.beta(torch.cat([sx, x.detach()], 1))
        return st + s_fn.hamiltonian(beta)[:, 0]


def step_map(
    s_fn: PolynomialRealizationGenerating,
    xk: Tensor,
    h: float,
    tol: float = 1e-13,
    max_iter: int = 50,
) -> Tensor:
    """One step in torch (the oracle of the Rust step): Newton on α(x, ∇S(h, x)) = x_k from
    x = x_k with autograd Jacobians, then x_{k+1} = β(x, ∇S(h, x)). xk (B, n) float64 →
    (B, n); NaN rows where Newton fails."""
    n = xk.shape[1]
    t = torch.full((xk.shape[0],), float(h), dtype=xk.dtype)
    z = xk.detach().clone()
    converged = torch.zeros(xk.shape[0], dtype=torch.bool)
    for _ in range(max_iter):
        zv = z.detach().requires_grad_(True)
        with torch.enable_grad():
            (g,) = torch.autograd.grad(s_fn(t, zv).sum(), zv, create_graph=True)
            a = s_fn.alpha(torch.cat([g, zv], 1))
            jac = torch.stack(
                [torch.autograd.grad(a[:, i].sum(), zv, retain_graph=True)[0] for i in range(n)],
                1,
            )
        f = a.detach() - xk
        delta = torch.linalg.solve(jac.detach(), -f[..., None])[..., 0]
        z = z + delta
        scale = z.abs().amax(1).clamp_min(1.0)
        converged = delta.abs().amax(1) <= tol * scale
        if bool(converged.all()):
            break
    _, g = hj_derivatives(s_fn, t, z, create_graph=False)
    out = s_fn.beta(torch.cat([g, z], 1))
    return torch.where(converged[:, None], out.detach(), torch.full_like(out, float("nan")))


# ---------------------------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------------------------


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


@dataclass
class PolynomialTrainConfig(FitConfig):
    """Everything that determines a training run of a generating function on the order-n
    realization of a polynomial bivector (and is recorded in the model file). The defaults are
    sized for the cubic Nambu scene (scenes/nambu_cubic.toml: states (0.3, 0.5, −0.4),
    (0.1, −0.6, 0.3), h = 0.1), whose orbits stay in [−0.7, 0.7]³."""

    system: dict[str, Any] | PolynomialPoissonSystem
    """The system, or its ``to_dict()``; stored as the dictionary (JSON)."""
    taylor_order: int = 3
    """m: exact Taylor terms S_1..S_m in S (1..=5)."""
    realization_order: int | None = None
    """n: order of the realization (1..=MAX_REALIZATION_ORDER); default the matched odd order
    max(3, m + 1 − m mod 2) of :func:`matched_realization_order`."""
    mlp_power: int | None = None
    """M in t^M·N; default m + 2 where S_{m+1} vanishes, else m + 1."""
    widths: tuple[int, ...] = (16, 16)
    x_min: tuple[float, ...] = (-0.7, -0.7, -0.7)
    x_max: tuple[float, ...] = (0.7, 0.7, 0.7)
    h_max: float = 0.1
    batch: int = 1024
    iterations: int = 1000
    lr: float = 3e-3
    schedule: str = "cosine"
    seed: int = 0
    dtype: str = "float64"
    lbfgs_iterations: int = 0
    """L-BFGS iterations (strong-Wolfe line search) after Adam on one fixed seeded batch of
    ``lbfgs_batch`` points; 0: none."""
    lbfgs_batch: int = 4096

    def polish_batch(self) -> int:
        return self.lbfgs_batch

    def run_training(self, **options: Any) -> Any:
        """Trains this configuration: :func:`train_polynomial` (what
        :func:`poisson_rs.train.train` calls for it)."""
        return train_polynomial(self, **options)

    def __post_init__(self) -> None:
        if isinstance(self.system, PolynomialPoissonSystem):
            self.system = self.system.to_dict()
        if isinstance(self.widths, (list, tuple)):
            self.widths = tuple(self.widths)
        if isinstance(self.x_min, (list, tuple)):
            self.x_min = tuple(self.x_min)
        if isinstance(self.x_max, (list, tuple)):
            self.x_max = tuple(self.x_max)

    def poisson_system(self) -> PolynomialPoissonSystem:
        try:
            return _system_of(self.system)
        except (TypeError, ValueError, KeyError) as e:
            raise ValueError(f"PolynomialTrainConfig field system: {e}") from None

    def resolved_realization_order(self) -> int:
        if self.realization_order is not None:
            return self.realization_order
        return matched_realization_order(self.taylor_order)

    def validate(self) -> None:
        """Raises ValueError naming the first bad field."""
        system = self.poisson_system()
        n = system.dim
        ints = {
            "taylor_order": (self.taylor_order, 1, MAX_TAYLOR_ORDER),
            "batch": (self.batch, 1, 10_000_000),
            "iterations": (self.iterations, 0, 10**9),
            "seed": (self.seed, 0, 2**63 - 1),
            "lbfgs_iterations": (self.lbfgs_iterations, 0, 10**7),
            "lbfgs_batch": (self.lbfgs_batch, 1, 10_000_000),
        }
        if self.realization_order is not None:
            ints["realization_order"] = (self.realization_order, 1, MAX_REALIZATION_ORDER)
        if self.mlp_power is not None:
            ints["mlp_power"] = (self.mlp_power, 1, 64)
        for name, (v, lo, hi) in ints.items():
            if not is_int(v) or not lo <= v <= hi:
                raise ValueError(
                    f"PolynomialTrainConfig field {name}: {v!r} must be an integer in [{lo}, {hi}]"
                )
        if not isinstance(self.widths, tuple) or not all(
            is_int(w) and 1 <= w <= 100_000 for w in self.widths
        ):
            raise ValueError(
                f"PolynomialTrainConfig field widths: {self.widths!r} must be integers in "
                "[1, 100000]"
            )
        for name, x in (("h_max", self.h_max), ("lr", self.lr)):
            if not _is_number(x) or not 0 < x < math.inf:
                raise ValueError(
                    f"PolynomialTrainConfig field {name}: {x!r} must be a finite number > 0"
                )
        for name, box in (("x_min", self.x_min), ("x_max", self.x_max)):
            if (
                not isinstance(box, tuple)
                or len(box) != n
                or not all(_is_number(v) and math.isfinite(v) for v in box)
            ):
                raise ValueError(
                    f"PolynomialTrainConfig field {name}: {box!r} must be {n} finite numbers"
                )
        if not all(a < b for a, b in zip(self.x_min, self.x_max, strict=True)):
            raise ValueError(
                f"PolynomialTrainConfig field x_max: need x_min < x_max, got {self.x_min}, "
                f"{self.x_max}"
            )
        if self.schedule not in ("cosine", "constant"):
            raise ValueError(
                f"PolynomialTrainConfig field schedule: {self.schedule!r} ('cosine' or 'constant')"
            )
        if self.dtype not in ("float32", "float64"):
            raise ValueError(
                f"PolynomialTrainConfig field dtype: {self.dtype!r} ('float32' or 'float64')"
            )

    def domain_dict(self) -> dict[str, Any]:
        return {
            "kind": "box",
            "x_min": list(self.x_min),
            "x_max": list(self.x_max),
            "t_max": self.h_max,
        }

    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """(center, half width) of the training box."""
        lo, hi = np.array(self.x_min, np.float64), np.array(self.x_max, np.float64)
        return 0.5 * (lo + hi), 0.5 * (hi - lo)


def sample_points(
    cfg: PolynomialTrainConfig, n: int, gen: torch.Generator, dtype: torch.dtype
) -> tuple[Tensor, Tensor]:
    """n points: t (n,) uniform in [0, h_max], x (n, dim) uniform in the box."""
    return box_points(cfg.box(), cfg.h_max, n, gen, dtype)


def build_model(
    cfg: PolynomialTrainConfig, tables: RealizationTables | None = None
) -> PolynomialRealizationGenerating:
    """The untrained model (seeded; last layer zero, so S starts as the Taylor terms). The
    network's output is scaled by the RMS over the box of S_M, the first term it stands in for
    (1 where it vanishes)."""
    cfg.validate()
    system = cfg.poisson_system()
    m, n = cfg.taylor_order, cfg.resolved_realization_order()
    if tables is None:
        tables = realization_tables(system, m, n)
    power = cfg.mlp_power
    if power is None:
        power = m + 2 if tables.next_term_vanishes else m + 1
    dtype = getattr(torch, cfg.dtype)
    center, half = cfg.box()
    out_scale = 1.0
    if power <= MAX_TAYLOR_ORDER + 1:
        terms = hj_series(system, power, n)
        gen = torch.Generator().manual_seed(cfg.seed + 1)
        _, x = sample_points(cfg, 2048, gen, torch.float64)
        _, co, ex = _term_table([terms[power - 1]], system.structure.x)
        vals = TermPolynomials((np.zeros(len(co), np.int64), co, ex), 1)(x)[:, 0].numpy()
        out_scale = float(np.sqrt(np.mean(vals**2))) or 1.0
    torch.manual_seed(cfg.seed)
    s_fn = PolynomialRealizationGenerating(
        tables, system.dim, m, n, cfg.widths, power, center, half, cfg.h_max, out_scale, dtype
    )
    if len(s_fn.linears):
        s_fn.zero_output_layer()
    return s_fn


#: The result of :func:`train_polynomial`.
PolynomialTrainResult = PinnResult


#: r(S, t, x, create_graph) → (B,): the HJ residual a model is trained on.
ModelResidual = Callable[[PolynomialRealizationGenerating, Tensor, Tensor, bool], Tensor]


def train_polynomial(
    cfg: PolynomialTrainConfig,
    *,
    progress: bool = True,
    log_every: int = 10,
    callback: Callable[[int, float], None] | None = None,
    max_seconds: float | None = None,
    model: PolynomialRealizationGenerating | None = None,
    residual: ModelResidual | None = None,
) -> PinnResult:
    """Trains S = Taylor terms + t^M·N on the mean squared HJ residual of the order-n
    realization (:func:`~poisson_rs.realizations.pinn.fit`: Adam, then ``lbfgs_iterations`` of
    L-BFGS). ``progress`` shows a tqdm bar; ``max_seconds`` ends the run cleanly once that much
    time has passed. ``model`` (default :func:`build_model` of ``cfg``) and ``residual``
    (default :func:`hj_residual`, the system's own H) let another H be trained for on the same
    realization (:mod:`.expression_hj`)."""
    cfg.validate()
    s_fn = model if model is not None else build_model(cfg)
    tables = s_fn.tables
    of = residual if residual is not None else hj_residual

    def objective(s: torch.nn.Module, t: Tensor, x: Tensor, create_graph: bool) -> Tensor:
        # ``fit`` passes back the model it trains or one ``bare`` built: both are this class.
        return of(cast(PolynomialRealizationGenerating, s), t, x, create_graph)

    def sample(n: int, gen: torch.Generator, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        return sample_points(cfg, n, gen, dtype)

    return fit(
        cfg,
        s_fn,
        lambda: build_model(dataclasses.replace(cfg, dtype="float64"), tables),
        objective,
        sample,
        progress=progress,
        log_every=log_every,
        callback=callback,
        max_seconds=max_seconds,
    )


# ---------------------------------------------------------------------------------------------
# Model files
# ---------------------------------------------------------------------------------------------


def model_tensors(s_fn: PolynomialRealizationGenerating) -> dict[str, np.ndarray]:
    """The file's tensors: the tables of β, α and the Taylor part (:data:`TABLE_TENSORS`) and
    ``mlp.{i}.weight``/``.bias`` on raw inputs (t, x)."""
    tb = s_fn.tables
    tensors: dict[str, np.ndarray] = {}
    for prefix, (index, coeffs, exponents) in (("sou", tb.beta), ("tar", tb.alpha)):
        tensors[f"{prefix}.index"] = np.ascontiguousarray(index, dtype=np.int64)
        tensors[f"{prefix}.coeffs"] = np.ascontiguousarray(coeffs, dtype=np.float64)
        tensors[f"{prefix}.exponents"] = np.ascontiguousarray(exponents, dtype=np.int64)
    tensors["taylor.coeffs"] = np.ascontiguousarray(tb.taylor[1], dtype=np.float64)
    tensors["taylor.exponents"] = np.ascontiguousarray(tb.taylor[2], dtype=np.int64)
    for i, (w, b) in enumerate(s_fn.exported_layers()):
        tensors[f"mlp.{i}.weight"] = np.ascontiguousarray(w, dtype=np.float64)
        tensors[f"mlp.{i}.bias"] = np.ascontiguousarray(b, dtype=np.float64)
    return tensors


def core_model(s_fn: PolynomialRealizationGenerating) -> Any:
    """The Rust model of ``s_fn`` (``_core.LearnedModel`` on the polynomial realization)."""
    return core_from_tensors(model_tensors(s_fn), s_fn.mlp_power)


def core_from_tensors(tensors: Mapping[str, np.ndarray], mlp_power: int) -> Any:
    from .. import _core

    n_layers = sum(1 for k in tensors if k.startswith("mlp.") and k.endswith(".weight"))
    # By name rather than ``*(tensors[k] for k in TABLE_TENSORS)``: a starred generator hides
    # from the type checker which argument each array is.
    return _core.LearnedModel.from_polynomial_tables(
        tensors["sou.index"],
        tensors["sou.coeffs"],
        tensors["sou.exponents"],
        tensors["tar.index"],
        tensors["tar.coeffs"],
        tensors["tar.exponents"],
        tensors["taylor.coeffs"],
        tensors["taylor.exponents"],
        [tensors[f"mlp.{i}.weight"] for i in range(n_layers)],
        [tensors[f"mlp.{i}.bias"] for i in range(n_layers)],
        int(mlp_power),
    )


def model_bytes(
    s_fn: PolynomialRealizationGenerating,
    cfg: PolynomialTrainConfig,
    record: Mapping[str, Any] | None = None,
) -> bytes:
    """The model file of ``s_fn`` (safetensors): :func:`model_tensors`; metadata ``format``,
    ``structure = polynomial``, ``system`` (JSON: the bivector's entries or Nambu Casimir and
    the Hamiltonian), ``taylor_order`` m, ``realization_order`` n, ``mlp_power``,
    ``mlp_inputs = t,x``, ``widths``, ``h_max``, ``domain`` (JSON), and ``record`` entries
    (non-strings as JSON). Refuses NaN or infinite weights (a diverged run)."""
    tensors = {k: v for k, v in model_tensors(s_fn).items() if not k.startswith("mlp.")}
    return model_file(
        tensors,
        s_fn,
        cfg,
        structure=STRUCTURE,
        system=cfg.poisson_system(),
        inputs="t,x",
        fields={"realization_order": str(s_fn.realization_order)},
        record=record,
    )


def save_result(
    result: PolynomialTrainResult,
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


_DTYPES = {"F64": np.dtype("<f8"), "I64": np.dtype("<i8")}
_REQUIRED = (
    "format",
    "structure",
    "system",
    "taylor_order",
    "realization_order",
    "h_max",
    "domain",
    "widths",
)


#: What a polynomial in a model file may be written with: variables x1..x99, decimal numbers,
#: + − * / ** and parentheses. sympy parses text with eval, so a file's text is checked first.
_POLYNOMIAL_TEXT = re.compile(r"(?:x\d{1,2}|\d+(?:\.\d*)?(?:[eE][-+]?\d+)?|\*\*|[-+*/() ])*")


def _check_expressions(spec: Any) -> None:
    """Refuses a system dictionary whose polynomial texts hold anything but numbers, x1..x99 and
    arithmetic (ValueError naming the text)."""
    if not isinstance(spec, dict):
        raise ValueError(f"metadata 'system' must be a JSON object, got {type(spec).__name__}")
    texts = [spec.get("hamiltonian"), spec.get("casimir")]
    entries = spec.get("entries") or []
    if not isinstance(entries, list):
        raise ValueError("metadata 'system' field entries must be a list")
    texts += [e[2] for e in entries if isinstance(e, list) and len(e) == 3]
    for text in texts:
        if text is None:
            continue
        if not isinstance(text, str) or len(text) > 100_000 or not _POLYNOMIAL_TEXT.fullmatch(text):
            raise ValueError(
                f"polynomial {str(text)[:60]!r} may hold only numbers, x1..x99, + - * / ** and "
                "parentheses"
            )


def read_model_file(data: bytes, source: str = "model bytes") -> tuple[dict[str, Any], Any]:
    """Parses a polynomial-realization model file: (decoded metadata, ``_core`` model).

    The metadata's ``system`` becomes a :class:`PolynomialPoissonSystem`, ``taylor_order`` and
    ``realization_order`` integers in range, ``h_max`` a positive float, ``domain`` a box. The
    tensors (:data:`TABLE_TENSORS`, ``mlp.{i}.*``) are checked and handed to the core, which
    checks the polynomials. Any problem raises one :class:`~poisson_rs.untrusted.InputError`
    (ValueError) naming ``source`` and the field."""
    from ..export import FORMAT
    from ..untrusted import parsing

    with parsing(source):
        if len(data) < 8:
            raise ValueError("not a safetensors file (shorter than its 8-byte header length)")
        size = int.from_bytes(data[:8], "little")
        if not 0 < size <= len(data) - 8:
            raise ValueError(f"header length {size} does not fit the file ({len(data)} bytes)")
        header = json.loads(data[8 : 8 + size])
        if not isinstance(header, dict):
            raise ValueError("the header is not a JSON object")
        raw = header.pop("__metadata__", None)
        if not isinstance(raw, dict) or not all(isinstance(v, str) for v in raw.values()):
            raise ValueError("the file has no string metadata; is it a poisson_rs model?")
        missing = [k for k in _REQUIRED if k not in raw]
        if missing:
            raise ValueError(f"model metadata lacks {', '.join(missing)}")
    with parsing(source, "format"):
        if raw["format"] != FORMAT:
            raise ValueError(f"format is {raw['format'][:60]!r}, expected {FORMAT!r}")
    with parsing(source, "structure"):
        if raw["structure"] != STRUCTURE:
            raise ValueError(f"structure is {raw['structure'][:40]!r}, not {STRUCTURE!r}")
    meta: dict[str, Any] = dict(raw)
    with parsing(source, "system"):
        spec = json.loads(raw["system"])
        _check_expressions(spec)
        meta["system"] = PolynomialPoissonSystem.from_dict(spec)
    dim = meta["system"].dim
    for key, hi in (
        ("taylor_order", MAX_TAYLOR_ORDER),
        ("realization_order", MAX_REALIZATION_ORDER),
    ):
        with parsing(source, key):
            value = int(raw[key])
            if str(value) != raw[key].strip() or not 1 <= value <= hi:
                raise ValueError(
                    f"metadata {key!r} must be an integer in 1..={hi}, got {raw[key]!r}"
                )
            meta[key] = value
    with parsing(source, "h_max"):
        meta["h_max"] = float(raw["h_max"])
        if not 0 < meta["h_max"] < math.inf:
            raise ValueError(f"metadata 'h_max' must be a finite number > 0, got {raw['h_max']!r}")
    with parsing(source, "widths"):
        widths = json.loads(raw["widths"])
        if not isinstance(widths, list) or not all(is_int(w) and w > 0 for w in widths):
            raise ValueError(f"metadata 'widths' must be a list of positive integers: {widths!r}")
        meta["widths"] = tuple(widths)
    with parsing(source, "domain"):
        domain = json.loads(raw["domain"])
        ok = isinstance(domain, dict) and domain.get("kind") == "box"
        bounds: list[Any] = [domain.get(k) if ok else None for k in ("x_min", "x_max")]
        lo, hi = bounds
        ok = ok and all(
            isinstance(v, list) and len(v) == dim and all(_is_number(a) for a in v)
            for v in (lo, hi)
        )
        if not ok or not all(a < b for a, b in zip(lo, hi, strict=True)):
            raise ValueError(
                f"metadata 'domain' must be a box with {dim} bounds x_min < x_max: "
                f"{raw['domain'][:80]!r}"
            )
        meta["domain"] = domain
    tensors: dict[str, np.ndarray] = {}
    base = 8 + size
    for name, entry in header.items():
        with parsing(source, f"tensor {str(name)[:40]}"):
            known = name in TABLE_TENSORS or (
                name.startswith("mlp.") and name.endswith((".weight", ".bias"))
            )
            if not known:
                raise ValueError(f"unexpected tensor {name[:40]!r}")
            dtype = _DTYPES[entry["dtype"]]
            shape = [int(s) for s in entry["shape"]]
            a, b = (int(v) for v in entry["data_offsets"])
            if not 0 <= a <= b <= len(data) - base or b - a != dtype.itemsize * math.prod(shape):
                raise ValueError(f"data_offsets {entry['data_offsets']} do not fit its shape")
            tensors[name] = np.frombuffer(data[base + a : base + b], dtype=dtype).reshape(shape)
    with parsing(source, "tensors"):
        missing = [k for k in TABLE_TENSORS if k not in tensors]
        if missing:
            raise ValueError(f"the file lacks the tensors {', '.join(missing)}")
        n_layers = sum(1 for k in tensors if k.endswith(".weight"))
        for i in range(n_layers):
            for part in ("weight", "bias"):
                if f"mlp.{i}.{part}" not in tensors:
                    raise ValueError(f"the file lacks the tensor mlp.{i}.{part}")
        if tensors["taylor.exponents"].ndim != 2 or tensors["taylor.exponents"].shape[1] != dim + 1:
            raise ValueError(
                f"taylor.exponents must have {dim + 1} columns (t, x) for the {dim}-dimensional "
                "system of the metadata"
            )
    with parsing(source, "widths"):
        held = [int(tensors[f"mlp.{i}.weight"].shape[0]) for i in range(n_layers - 1)]
        if list(meta["widths"]) != held:
            raise ValueError(
                f"metadata 'widths' says {list(meta['widths'])} but the tensors hold {held}"
            )
    with parsing(source, "mlp_power"):
        # The network's power of t is part of S: a file with a network must state it (a
        # default would step another S), as the other structures' files must.
        if n_layers and "mlp_power" not in raw:
            raise ValueError("metadata 'mlp_power' is missing (the file holds a network)")
        power = int(raw.get("mlp_power", "1"))
        if str(power) != raw.get("mlp_power", "1").strip() or not 1 <= power <= 64:
            raise ValueError(f"metadata 'mlp_power' must be in 1..=64, got {raw['mlp_power']!r}")
        meta["mlp_power"] = power
    with parsing(source, "mlp_inputs"):
        if raw.get("mlp_inputs", "t,x") != "t,x":
            raise ValueError(f"metadata 'mlp_inputs' must be 't,x', got {raw['mlp_inputs']!r}")
    with parsing(source):
        core = core_from_tensors(tensors, power)  # checks the tables' shapes and values
    _check_tables(tensors, meta, source)
    return meta, core


def _rows(table: Table) -> tuple[np.ndarray, np.ndarray]:
    """A term table as (keys (K, 1 + V): index then exponents, coeffs) for :func:`terms_agree`."""
    index, coeffs, exponents = table
    return np.c_[np.asarray(index).reshape(-1, 1), exponents], coeffs


def _check_tables(tensors: Mapping[str, np.ndarray], meta: Mapping[str, Any], source: str) -> None:
    """InputError unless the file's tables are those its metadata derives: the core steps the
    tables, the studies score ``system``, so a file whose metadata was edited would step one
    system and report another. Checked from the cheapest to the costliest, each naming its
    field: the t¹ terms of S are −H (``system``); β's terms of degree 1 in p are −½π p (the
    bivector, ``system``); β and α are the realization of ``realization_order``; the Taylor
    table is S_1..S_m of ``taylor_order``."""
    from ..export import terms_agree
    from ..untrusted import parsing

    system: PolynomialPoissonSystem = meta["system"]
    m, n = meta["taylor_order"], meta["realization_order"]
    dim = system.dim
    x = system.structure.x
    t_exps, t_coeffs = tensors["taylor.exponents"], tensors["taylor.coeffs"]
    sou = (tensors["sou.index"], tensors["sou.coeffs"], tensors["sou.exponents"])
    tar = (tensors["tar.index"], tensors["tar.coeffs"], tensors["tar.exponents"])
    with parsing(source, "system"):
        _, h_coeffs, h_exps = _term_table([system.h], x)
        first = t_exps[:, 0] == 1
        want = (np.c_[np.ones((len(h_coeffs), 1), np.int64), h_exps], -h_coeffs)
        if not terms_agree((t_exps[first], t_coeffs[first]), want):
            raise ValueError(
                f"the file's t¹ terms are not -t·H of the system its metadata records "
                f"({system!r}): the metadata was edited or belongs to another model"
            )
        beta1, _, p = system.structure.realization(1)
        low = sou[2][:, :dim].sum(1) <= 1
        found = _rows((sou[0][low], sou[1][low], sou[2][low]))
        if not terms_agree(found, _rows(_term_table(beta1, (*p, *x)))):
            raise ValueError(
                f"the file's β is not x − ½π(x)p to first order in p for the bivector its "
                f"metadata records ({system!r}): the metadata was edited or belongs to another "
                "model"
            )
    tables = realization_tables(system, m, n)
    with parsing(source, "realization_order"):
        if not (
            terms_agree(_rows(sou), _rows(tables.beta))
            and terms_agree(_rows(tar), _rows(tables.alpha))
        ):
            raise ValueError(
                f"metadata 'realization_order' says {n} but the file's β and α are not the "
                f"order-{n} realization of its bivector"
            )
    with parsing(source, "taylor_order"):
        if not terms_agree((t_exps, t_coeffs), (tables.taylor[2], tables.taylor[1])):
            raise ValueError(
                f"metadata 'taylor_order' says {m} but the file's Taylor table is not "
                f"S_1..S_{m} of its system"
            )
