"""Training generating functions as PINNs: minimise the mean squared Hamilton–Jacobi residual

    r(t, p) = ∂S/∂t(t, p) + H(sou(∂S/∂p(t, p), p))

at sampled (t, p), t ∈ [0, h_max] and p in a cube or a spherical shell of g* ≅ Rⁿ (the paper's
eq. HJML), for any Lie–Poisson system (the rigid body by default).

Optionally (the paper's future work) a data term compares the model's one-step map with
trajectory pairs (μ_k, μ_{k+1}) at step h, and L-BFGS polishes the weights after Adam.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import io
import json
import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .devices import AUTO_DEVICE, auto_device, check_device
from .export import model_bytes, save_model
from .files import atomic_write_bytes, check_input_file, probe_writable
from .fit import (
    POLISH_SEED,
    SCALE_POINTS,
    SCALE_SEED,
    VALIDATION_POINTS,
    VALIDATION_SEED,
    AdamRun,
    FitConfig,
    adam_loop,
    check_run_options,
    lbfgs_polish,
)
from .fit import is_int as _is_int
from .generating import (
    MLP_INPUTS,
    GeneratingFunction,
    check_hj_derivatives,
    hj_derivatives,
    newton_system,
    solve_momentum,
)
from .realizations.lie_groupoid import check_chart, sou
from .structures.lie_poisson import LieAlgebra, LiePoissonSystem, RigidBody
from .taylor import evaluate_terms, system_taylor_terms
from .threads import MAX_THREADS_PER_CORE, cpu_cores, max_threads
from .untrusted import parsing


def check_threads(threads: Any, what: str = "threads") -> int:
    """``threads`` as an int in 1..:func:`max_threads`; TypeError/ValueError naming ``what``."""
    if not _is_int(threads):
        raise TypeError(f"{what} must be an integer, got {type(threads).__name__}")
    if not 1 <= threads <= max_threads():
        raise ValueError(
            f"{what} must lie in 1..{max_threads()} ({MAX_THREADS_PER_CORE} per core on this "
            f"machine's {cpu_cores()} core(s)), got {threads}"
        )
    return int(threads)


def default_threads() -> int:
    """The package's thread policy for training, shared by ``train()`` and the CLI: 1 on a
    machine with at most 2 cores (shared with other work, where more threads only contend:
    torch's default ran 5–75x slower there), else torch's own default, bounded."""
    if cpu_cores() <= 2:
        return 1
    return min(max(torch.get_num_threads(), 1), max_threads())


def resolve_threads(threads: int | None, what: str = "threads") -> int:
    """``threads`` checked (:func:`check_threads`), or :func:`default_threads` for None."""
    return default_threads() if threads is None else check_threads(threads, what)


def use_threads(threads: int | None, what: str = "threads") -> int:
    """Applies the thread policy to this process: torch's intra-op threads, and rayon's for the
    Rust rollouts unless RAYON_NUM_THREADS is set already. Returns the count used."""
    n = resolve_threads(threads, what)
    torch.set_num_threads(n)
    os.environ.setdefault("RAYON_NUM_THREADS", str(n))
    return n


@functools.lru_cache(maxsize=16)
def _decode_system(spec: str) -> LiePoissonSystem:
    """A system from its ``to_dict()`` as canonical JSON (systems are immutable: safe to share)."""
    return LiePoissonSystem.from_dict(json.loads(spec))


@dataclass
class TrainConfig(FitConfig):
    """Everything that determines a training run (and is recorded in the model file)."""

    inertia: tuple[float, float, float] = (1.5, 2.0, 2.5)
    """The rigid body's principal moments, when ``system`` is None."""
    system: dict[str, Any] | LiePoissonSystem | None = None
    """The Lie–Poisson system, or its ``to_dict()`` (``LiePoissonSystem.from_dict`` reads it);
    stored as the dictionary, so the configuration stays JSON (checkpoints, model files). None:
    the rigid body of ``inertia``."""
    chart: str = "cayley"
    widths: tuple[int, ...] = (8, 8)
    inputs: str = "homogeneous"
    """What the MLP sees: "t,p" (the paper) or "homogeneous" (see GeneratingFunction)."""
    taylor_order: int = 3
    """Exact Taylor terms S_1..S_K in the polynomial part (0: none, 1: S = −tH + …)."""
    mlp_power: int | None = None
    """m in t^m·MLP; default K + 2 for K ≥ 1 (S_{K+1} vanishes for odd K in the Cayley chart)."""
    domain: str = "shell"
    """Where training points p lie (see ``DOMAINS``): "shell" r_min ≤ |p| ≤ r_max, "cube"
    |pᵢ| ≤ half_width, or "top" for systems on se(3)* (p = (M, Γ)): |Mᵢ| ≤ half_width and
    r_min ≤ |Γ| ≤ r_max. |Γ|² is a Casimir, so a top's orbits keep |Γ| = 1; the cube of R⁶
    would spend most of its points where no orbit goes."""
    r_min: float = 1.0
    r_max: float = 4.0
    half_width: float = 3.0
    weight_power: float = 0.0
    """q ≥ 0: each HJ residual is divided by (1 + |p|²)^(q/2) in the loss. A Taylor base's residual
    grows with |p| (for the heavy top's K = 3 about 160x from |M| ≈ 0.5 to |M| ≈ 5), so an
    unweighted loss spends the fit on the domain's far corners, where few orbits go; 0: none
    (the homogeneous ansatz already divides by |p|²)."""
    h_max: float = 0.1
    batch: int = 2048
    n_points: int | None = None
    """Fixed pool of training points (the paper's 80,000); None draws fresh points every step."""
    iterations: int = 2000
    lr: float = 3e-3
    schedule: str = "cosine"
    seed: int = 0
    dtype: str = "float64"
    device: str = "auto"
    """Where training runs: "auto" (CUDA when torch sees a device, else the CPU: resolved when
    the configuration is made, so the recorded configuration names the device used), "cpu",
    "cuda" or "cuda:N". float64 on either; a model trained on a GPU is written to CPU tensors
    and loads anywhere."""
    derivatives: str = "reverse"
    """How the HJ loss takes ∂S/∂t and ∂S/∂p (``generating.hj_derivatives``): "reverse" (a
    hand-written backward pass; the faster on a CPU) or "autograd" (nested autograd: the paper
    preset's, and how the shipped models were trained). The loss agrees to rounding; a run's last
    bits, and so its path, differ."""
    lbfgs_iterations: int = 0
    """L-BFGS iterations (strong-Wolfe line search, several loss evaluations each) after Adam, on
    one fixed seeded batch of ``batch`` points; 0: none."""
    data_weight: float = 0.0
    """λ in loss = loss_HJ/loss_HJ(init) + λ·loss_data/loss_data(init); 0: no data term."""
    data_points: int = 0
    """Pairs (μ_k, μ_{k+1}) taken from the exact solution, one step of ``data_h`` from seeded
    random states of the training domain; 0: none (or pass ``train(data=...)``)."""
    data_h: float | None = None
    """Step h of the data pairs (time units); None: h_max."""
    sampling: str = "uniform"
    """Where training points p are drawn: "uniform" over the domain, or "scene": a fraction
    ``sampling_fraction`` of each batch near the exact orbits of ``sampling_states`` (the set a
    scene's trajectories visit), the rest uniform over the domain."""
    sampling_fraction: float = 0.5
    """Share of each batch drawn near the orbits in "scene" sampling, in [0, 1]."""
    sampling_states: tuple[tuple[float, float, float], ...] = ()
    """Initial states μ₀ whose exact orbits over [0, ``sampling_horizon``] "scene" sampling
    follows (units of μ)."""
    sampling_noise: float = 0.02
    """Standard deviation of the Gaussian offset of a scene point, relative to its |μ|."""
    sampling_horizon: float = 10.0
    """Time span of the orbits that "scene" sampling follows (time units)."""
    init: str = "zero"
    """How the network starts: "zero" (last layer's weight and bias zero, so S starts as the
    exact Taylor terms and training improves on the series) or "xavier" (every layer
    Xavier-uniform: the paper's, and how models recorded without this field were trained)."""

    def __post_init__(self) -> None:
        # A system object is kept as its dictionary: the configuration is recorded as JSON.
        if self.system is not None and not isinstance(self.system, Mapping):
            self.system = self.system.to_dict()
        if self.device == AUTO_DEVICE:
            self.device = auto_device()

    def resolved_mlp_power(self) -> int:
        if self.mlp_power is not None:
            return self.mlp_power
        return 1 if self.taylor_order == 0 else self.taylor_order + 2

    def lie_system(self) -> LiePoissonSystem:
        """The system trained for: ``system`` decoded, or the rigid body of ``inertia``. The
        training loop asks for it every batch, so decoding (and the Jacobi check that comes with
        it) happens once per distinct system."""
        if self.system is None:
            return RigidBody(tuple(self.inertia))  # type: ignore[arg-type]
        if not isinstance(self.system, Mapping):  # a system object assigned after construction
            return self.system
        _refuse_log_canonical(self.system)
        with parsing("TrainConfig", "system"):
            return _decode_system(json.dumps(self.system, sort_keys=True))

    def validate(self) -> None:
        """Raises ValueError naming the first bad setting."""
        check_chart(self.chart)
        if len(self.inertia) != 3 or not all(math.isfinite(i) and i > 0 for i in self.inertia):
            raise ValueError(f"inertia must be 3 positive numbers, got {self.inertia}")
        system = self.lie_system()
        if not system.algebra.is_so3() and self.chart != "exp":
            raise ValueError(
                f"the {self.chart!r} chart exists for so(3) only; use chart 'exp' for {system!r}"
            )
        if self.inputs == "homogeneous" and not system.polynomial.is_homogeneous(2):
            raise ValueError(
                "inputs 'homogeneous' builds in the scaling of a quadratic Hamiltonian; "
                f"{system!r} is not homogeneous quadratic: use inputs 't,p'"
            )
        if self.domain not in DOMAINS:
            raise ValueError(f"domain must be one of {DOMAINS}, got {self.domain!r}")
        if self.domain in ("shell", "top") and not 0 <= self.r_min < self.r_max:
            raise ValueError(f"need 0 <= r_min < r_max, got {self.r_min}, {self.r_max}")
        if self.domain in ("cube", "top") and not self.half_width > 0:
            raise ValueError(f"half_width must be > 0, got {self.half_width}")
        if self.domain == "top" and system.algebra != LieAlgebra.se3():
            raise ValueError(f"domain 'top' is (M, Γ) in se(3)*; {system!r} is not on se(3)*")
        self._validate_numbers()
        checks = [
            ("h_max", self.h_max > 0),
            ("batch", self.batch >= 1),
            ("iterations", self.iterations >= 0),
            ("lr", self.lr > 0),
            ("taylor_order", 0 <= self.taylor_order <= 15),
            ("widths", all(w >= 1 for w in self.widths)),
            ("mlp_power", self.resolved_mlp_power() >= 1),
            ("n_points", self.n_points is None or self.n_points >= 1),
            ("lbfgs_iterations", _is_int(self.lbfgs_iterations) and self.lbfgs_iterations >= 0),
            ("data_weight", math.isfinite(self.data_weight) and self.data_weight >= 0),
            ("data_points", _is_int(self.data_points) and self.data_points >= 0),
            ("data_h", self.data_h is None or (math.isfinite(self.data_h) and self.data_h > 0)),
            ("weight_power", 0 <= self.weight_power <= 16),
        ]
        for name, ok in checks:
            if not ok:
                raise ValueError(f"invalid {name}: {getattr(self, name)!r}")
        if self.data_points > 0 and self.data_weight == 0:
            raise ValueError("data_points > 0 needs data_weight > 0 (the pairs would be unused)")
        if self.inputs not in MLP_INPUTS:
            raise ValueError(f"inputs must be one of {MLP_INPUTS}, got {self.inputs!r}")
        if self.schedule not in ("cosine", "constant"):
            raise ValueError(f"schedule must be 'cosine' or 'constant', got {self.schedule!r}")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be 'float32' or 'float64', got {self.dtype!r}")
        check_hj_derivatives(self.derivatives)
        if self.init not in INIT:
            raise ValueError(f"init must be one of {INIT}, got {self.init!r}")
        self._validate_sampling()
        if not isinstance(self.device, str):
            raise ValueError(
                f"device must be a string such as 'cuda' or 'cpu', got {self.device!r}"
            )
        check_device(self.device, instead="use device='cpu' (or 'auto': CUDA where torch sees it)")

    def _validate_numbers(self) -> None:
        """Types, finiteness and sane ranges: an inf or absurd setting would train to NaN and
        report success. Lengths and times are bounded so that r_max³ and the loss (~|p|⁴) stay
        finite in float64; sizes so that a batch fits in memory."""
        reals = {
            "h_max": self.h_max,
            "lr": self.lr,
            "r_min": self.r_min,
            "r_max": self.r_max,
            "half_width": self.half_width,
            "weight_power": self.weight_power,
        }
        for name, v in reals.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"invalid {name}: {v!r} (must be a finite number)")
            if abs(v) > _MAX_MAGNITUDE:
                raise ValueError(f"invalid {name}: {v!r} (must not exceed {_MAX_MAGNITUDE:g})")
        ints = {
            "batch": (self.batch, _MAX_POINTS),
            "iterations": (self.iterations, 10**9),
            "taylor_order": (self.taylor_order, 15),
            "seed": (self.seed, 2**63 - 1),
        }
        if self.n_points is not None:
            ints["n_points"] = (self.n_points, _MAX_POINTS)
        if self.mlp_power is not None:
            ints["mlp_power"] = (self.mlp_power, 64)
        for name, (v, high) in ints.items():
            if not _is_int(v) or not 0 <= v <= high:
                raise ValueError(f"invalid {name}: {v!r} (must be an integer in [0, {high}])")
        if not all(_is_int(w) and 1 <= w <= _MAX_WIDTH for w in self.widths):
            raise ValueError(f"invalid widths: {self.widths!r} (integers in [1, {_MAX_WIDTH}])")
        for mu in self.sampling_states:
            if any(isinstance(v, (int, float)) and abs(v) > _MAX_MAGNITUDE for v in mu):
                raise ValueError(
                    f"sampling_states must be finite and not exceed {_MAX_MAGNITUDE:g}, got {mu!r}"
                )

    def _validate_sampling(self) -> None:
        if self.sampling not in SAMPLING:
            raise ValueError(f"sampling must be one of {SAMPLING}, got {self.sampling!r}")
        f = self.sampling_fraction
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0.0 <= f <= 1.0:
            raise ValueError(f"sampling_fraction must be a number in [0, 1], got {f!r}")
        if not (math.isfinite(self.sampling_noise) and self.sampling_noise >= 0):
            raise ValueError(f"sampling_noise must be finite and >= 0, got {self.sampling_noise}")
        if not (math.isfinite(self.sampling_horizon) and self.sampling_horizon > 0):
            raise ValueError(f"sampling_horizon must be > 0, got {self.sampling_horizon}")
        states = self.sampling_states
        if self.sampling == "uniform" and states:
            raise ValueError("sampling_states given but sampling is 'uniform' (unused)")
        if self.sampling == "scene" and not states:
            raise ValueError("sampling = 'scene' needs sampling_states (initial states)")
        dim = self.lie_system().dim
        for mu in states:
            if len(mu) != dim or not all(math.isfinite(v) for v in mu) or not any(mu):
                raise ValueError(
                    f"sampling_states must be non-zero finite {dim}-vectors, got {mu!r}"
                )

    def resolved_data_h(self) -> float:
        return self.h_max if self.data_h is None else self.data_h

    def domain_dict(self) -> dict[str, Any]:
        if self.domain == "cube":
            return {"kind": "cube", "half_width": self.half_width, "t_max": self.h_max}
        if self.domain == "top":
            return {
                "kind": "top",
                "half_width": self.half_width,
                "r_min": self.r_min,
                "r_max": self.r_max,
                "t_max": self.h_max,
            }
        return {"kind": "shell", "r_min": self.r_min, "r_max": self.r_max, "t_max": self.h_max}

    def input_radius(self) -> float:
        """A bound on |p| over the domain: the MLP sees p divided by it (inputs of order one)."""
        if self.domain == "cube":
            return self.half_width * math.sqrt(self.lie_system().dim)
        if self.domain == "top":
            # M and Γ scaled alike, so that each of the cube's and the shell's extents is O(1).
            return max(self.half_width, self.r_max)
        return self.r_max


def _refuse_log_canonical(system: Any) -> None:
    """ValueError for a log-canonical system given to the Lie–Poisson configuration, saying
    which configuration trains it."""
    kind = system.get("kind") if isinstance(system, Mapping) else getattr(system, "kind", None)
    if kind == "log_canonical":
        raise ValueError(
            "TrainConfig field system: a log-canonical system is trained with "
            "LogCanonicalTrainConfig (poisson_rs.realizations.log_canonical_hj), not TrainConfig"
        )


#: Values of ``TrainConfig.domain``.
DOMAINS = ("cube", "shell", "top")
#: Values of ``TrainConfig.sampling``.
SAMPLING = ("uniform", "scene")
#: Values of ``TrainConfig.init``.
INIT = ("zero", "xavier")

#: Largest |value| of a length or time setting (r_max, h_max, ...): r_max³ and |p|⁴ stay finite.
_MAX_MAGNITUDE = 1e50
#: Largest batch or point pool: 10⁷ points × 4 inputs × 8 bytes, times the layers, fits in memory.
_MAX_POINTS = 10_000_000
#: Largest hidden layer width.
_MAX_WIDTH = 100_000

#: Named configurations. "paper" is the paper's setting, exactly where it is stated.
PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "paper": {
        # 80,000 points uniform in [−3, 3]³; 500-250-250-250 tanh, Xavier-uniform; Adam, lr 1e-4,
        # 10,000 iterations; S = t·MLP. The t range and float precision are not stated: we use
        # t ∈ [0, 0.1] (the scene's step) and torch's default float32.
        "widths": (500, 250, 250, 250),
        "taylor_order": 0,
        "mlp_power": 1,
        "inputs": "t,p",
        "domain": "cube",
        "half_width": 3.0,
        "n_points": 80_000,
        "batch": 80_000,
        "iterations": 10_000,
        "lr": 1e-4,
        "schedule": "constant",
        "dtype": "float32",
        # Not the paper's choice but ours: nested autograd is the faster on the GPU this preset
        # is trained on (README, Performance), and it is how the shipped model was trained.
        "derivatives": "autograd",
        "init": "xavier",
    },
}


def hamiltonian(system: Sequence[float] | LiePoissonSystem, mu: Tensor) -> Tensor:
    """H(μ) for μ (..., n) → (...,): the system's own H, or ½ Σ μᵢ²/Iᵢ for a rigid body given by
    its inertia (the loop's hot path: no system built per batch)."""
    if isinstance(system, Sequence):
        inv = torch.tensor([1.0 / i for i in system], dtype=mu.dtype, device=mu.device)
        return 0.5 * (mu * mu * inv).sum(-1)
    return system.hamiltonian(mu)


def solution(system: LiePoissonSystem, states: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The flow of ``system`` from states (m, n) at times: the system's own reference (the
    closed form for a rigid body, a tight DOP853 reference otherwise). → (m, len(times), n)."""
    return system.reference(states, times)


def sample_points(
    cfg: TrainConfig, n: int, gen: torch.Generator, dtype: torch.dtype, device: str
) -> tuple[Tensor, Tensor]:
    """n training points: t (n,) uniform in [0, h_max] and p (n, dim) as ``cfg.sampling`` says
    (uniform in the domain, or partly near the scene's orbits: :func:`_sample_orbits`)."""
    if cfg.sampling == "uniform":
        return _sample_domain(cfg, n, gen, dtype, device)
    n_orbit = round(cfg.sampling_fraction * n)
    t, p = _sample_domain(cfg, n - n_orbit, gen, dtype, device)
    if n_orbit == 0:
        return t, p
    t_orbit = torch.rand(n_orbit, generator=gen, dtype=dtype) * cfg.h_max
    p_orbit = _sample_orbits(cfg, n_orbit, gen, dtype)
    return torch.cat([t, t_orbit.to(device)]), torch.cat([p, p_orbit.to(device)])


#: Times per orbit in the pool that "scene" sampling draws from: a spacing of T/2047 (0.005 at
#: T = 10) is far below the noise the points get.
_ORBIT_TIMES = 2048


def _system_key(cfg: TrainConfig) -> str:
    """The configuration's system as canonical JSON: the cache key of what depends on it."""
    spec = cfg.system if cfg.system is not None else cfg.lie_system().to_dict()
    return json.dumps(spec, sort_keys=True)


@functools.lru_cache(maxsize=8)
def _orbit_pool(
    system_json: str,
    states: tuple[tuple[float, ...], ...],
    horizon: float,
) -> np.ndarray:
    """Points of the exact orbits of ``states`` at evenly spaced times in [0, horizon]:
    (n_states · _ORBIT_TIMES, dim) float64, computed once per configuration."""
    system = _decode_system(system_json)
    times = np.linspace(0.0, horizon, _ORBIT_TIMES)
    traj = solution(system, np.asarray(states, np.float64), times)
    return traj.reshape(-1, system.dim)


def _sample_orbits(cfg: TrainConfig, n: int, gen: torch.Generator, dtype: torch.dtype) -> Tensor:
    """n points near the set the scene visits: exact orbit points μ(τ) of ``sampling_states``
    (τ uniform in [0, sampling_horizon], states equally weighted) plus an isotropic Gaussian
    offset of σ = sampling_noise·|μ|. The offset covers where Newton's p lies: within O(h²)·|μ|
    of the orbit (p ≈ μ(h/2) to first order), and the numerical trajectory's drift off it."""
    states = tuple(tuple(float(v) for v in mu) for mu in cfg.sampling_states)
    pool = torch.as_tensor(_orbit_pool(_system_key(cfg), states, cfg.sampling_horizon))
    idx = torch.randint(len(pool), (n,), generator=gen)
    q = pool[idx].to(dtype)
    noise = torch.randn(n, q.shape[1], generator=gen, dtype=dtype)
    return q + cfg.sampling_noise * q.norm(dim=1, keepdim=True) * noise


def _sample_domain(
    cfg: TrainConfig, n: int, gen: torch.Generator, dtype: torch.dtype, device: str
) -> tuple[Tensor, Tensor]:
    """n points uniform in the training domain: t (n,) in [0, h_max], p (n, dim) in the cube,
    the shell or the top domain (``TrainConfig.domain``)."""
    dim = cfg.lie_system().dim
    t = torch.rand(n, generator=gen, dtype=dtype) * cfg.h_max
    if cfg.domain == "cube":
        p = (2.0 * torch.rand(n, dim, generator=gen, dtype=dtype) - 1.0) * cfg.half_width
    elif cfg.domain == "top":
        m = (2.0 * torch.rand(n, 3, generator=gen, dtype=dtype) - 1.0) * cfg.half_width
        d = torch.randn(n, 3, generator=gen, dtype=dtype)
        # |Γ| uniform in [r_min, r_max] (not in volume): the shell is thin about |Γ| = 1.
        r = cfg.r_min + torch.rand(n, 1, generator=gen, dtype=dtype) * (cfg.r_max - cfg.r_min)
        p = torch.cat([m, d / d.norm(dim=1, keepdim=True) * r], 1)
    else:
        # Uniform in volume: rⁿ uniform between r_minⁿ and r_maxⁿ.
        d = torch.randn(n, dim, generator=gen, dtype=dtype)
        d = d / d.norm(dim=1, keepdim=True)
        u = torch.rand(n, 1, generator=gen, dtype=dtype)
        r = (cfg.r_min**dim + u * (cfg.r_max**dim - cfg.r_min**dim)) ** (1.0 / dim)
        p = d * r
    return t.to(device), p.to(device)


def hj_residual(
    s_fn: GeneratingFunction,
    inertia: Sequence[float] | LiePoissonSystem,
    t: Tensor,
    p: Tensor,
    create_graph: bool,
    *,
    derivatives: str = "reverse",
) -> Tensor:
    """r = ∂S/∂t + H(sou(∂S/∂p, p)), the derivatives by ``hj_derivatives(method=derivatives)``;
    differentiable in the MLP parameters if ``create_graph``. t (B,), p (B, n) → (B,), in units
    of energy. ``inertia`` is the system (or, for a rigid body, its moments of inertia).

    For a homogeneous S the residual scales as r(t, λp) = λ² r(λt, p).
    """
    st, sp = hj_derivatives(s_fn, t, p, method=derivatives, create_graph=create_graph)
    with torch.set_grad_enabled(create_graph):
        return _residual(s_fn, inertia, st, sp, p)


def _residual(
    s_fn: GeneratingFunction,
    system: Sequence[float] | LiePoissonSystem,
    st: Tensor,
    sp: Tensor,
    p: Tensor,
) -> Tensor:
    """r = ∂S/∂t + H(sou(∂S/∂p, p)) from the derivatives: (B,), in units of energy."""
    return st + hamiltonian(system, sou(s_fn.chart, sp, p.detach(), algebra=s_fn.algebra))


def build_model(cfg: TrainConfig) -> GeneratingFunction:
    """The untrained generating function of a configuration (seeded Xavier-uniform init).

    Inputs are scaled to O(1); the MLP output is scaled by the RMS of the first Taylor term it
    stands in for, S_m, so that the network starts at the right magnitude.
    """
    dtype = getattr(torch, cfg.dtype)
    system = cfg.lie_system()
    dim = system.dim
    m = cfg.resolved_mlp_power()
    powers, coeffs = (
        system_taylor_terms(system, cfg.taylor_order, cfg.chart)
        if cfg.taylor_order
        else (np.zeros((0, 1 + dim), np.int64), np.zeros(0))
    )
    r_scale = cfg.input_radius()
    homogeneous = cfg.inputs == "homogeneous"
    # Output scale: RMS over the domain of S_m (the term the MLP replaces first), per unit
    # |p|^(m+1) for the homogeneous ansatz.
    gen = torch.Generator().manual_seed(cfg.seed + 1)
    # Over the whole domain whatever the sampling: the same configuration starts from the same
    # network under uniform and scene sampling.
    _, p = _sample_domain(cfg, 2048, gen, torch.float64, "cpu")
    pw, cf = system_taylor_terms(system, max(m, 1), cfg.chart)
    sel = pw[:, 0] == m
    out_scale = 1.0
    if sel.any():
        vals = evaluate_terms(pw[sel], cf[sel], np.ones(len(p)), p.numpy())
        if homogeneous:
            vals = vals / np.linalg.norm(p.numpy(), axis=1) ** (m + 1)
        out_scale = float(np.sqrt(np.mean(vals**2))) or 1.0
    t_scale = 1.0 / (cfg.h_max * r_scale) if homogeneous else 1.0 / cfg.h_max
    p_scale = 1.0 if homogeneous else 1.0 / r_scale
    torch.manual_seed(cfg.seed)
    return GeneratingFunction(
        cfg.widths,
        mlp_power=m,
        powers=powers,
        coeffs=coeffs,
        chart=cfg.chart,
        inputs=cfg.inputs,
        input_scale=(t_scale, *(p_scale,) * dim),
        output_scale=out_scale,
        dtype=dtype,
        algebra=system.algebra,
    ).to(cfg.device)


def _loss(
    s_fn: GeneratingFunction, cfg: TrainConfig, t: Tensor, p: Tensor, create_graph: bool
) -> Tensor:
    """Mean squared HJ residual (eq. HJML); for the homogeneous ansatz each residual is divided by
    |p|², which makes every point weigh as its image on the unit sphere, and by
    (1 + |p|²)^(q/2) for ``cfg.weight_power`` q > 0."""
    st, sp = hj_derivatives(s_fn, t, p, method=cfg.derivatives, create_graph=create_graph)
    with torch.set_grad_enabled(create_graph):
        weight = None
        if cfg.weight_power:
            weight = (1.0 + (p * p).sum(1)) ** (-0.5 * cfg.weight_power)
        return loss_from_derivatives(s_fn, _loss_system(cfg), st, sp, p, weight=weight)


def _loss_system(cfg: TrainConfig) -> Sequence[float] | LiePoissonSystem:
    """What the loss evaluates H with: a rigid body's inertia (its closed form, as the shipped
    models were trained), else the system."""
    return cfg.inertia if cfg.system is None else cfg.lie_system()


def loss_from_derivatives(
    s_fn: GeneratingFunction,
    inertia: Sequence[float] | LiePoissonSystem,
    st: Tensor,
    sp: Tensor,
    p: Tensor,
    *,
    weight: Tensor | None = None,
) -> Tensor:
    """The mean squared HJ residual from ∂S/∂t (B,) and ∂S/∂p (B, n) however they were taken,
    at momenta p (B, n); for the homogeneous ansatz each residual is divided by |p|², and each is
    multiplied by ``weight`` (B,) when given. ``inertia`` is the system (or, for a rigid body,
    its moments of inertia)."""
    r = _residual(s_fn, inertia, st, sp, p)
    if s_fn.inputs == "homogeneous":
        r = r / (p * p).sum(1)
    if weight is not None:
        r = r * weight
    return r.pow(2).mean()


def data_from_exact(
    body: LiePoissonSystem, states: np.ndarray, h: float, n_steps: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Trajectory pairs from the exact flow (a tight reference for systems without a closed
    form): states (m, n), step h (time units), n_steps ≥ 1 steps each → (mu_k, mu_k1), both
    (m·n_steps, n) float64, μ_{k+1} = the flow of μ_k over h."""
    if not (_is_int(n_steps) and n_steps >= 1):
        raise ValueError(f"n_steps must be an integer >= 1, got {n_steps!r}")
    dim = body.dim
    states = np.asarray(states, dtype=np.float64).reshape(-1, dim)
    traj = solution(body, states, h * np.arange(n_steps + 1))  # (m, n_steps + 1, n)
    return traj[:, :-1].reshape(-1, dim), traj[:, 1:].reshape(-1, dim)


#: Newton cap for the data pairs: a pair that needs more is dropped from the data loss.
_DATA_NEWTON_ITERATIONS = 20


def _differentiable_step(s_fn: GeneratingFunction, mu: Tensor, p: Tensor, h: float) -> Tensor:
    """sou(∂S/∂p(h, p̃), p̃) after one Newton step p̃ = p − J⁻¹(tar(∂S/∂p(h, p), p) − μ) from the
    converged p with J held constant. In value p̃ = p; in the weights θ, dp̃/dθ = −J⁻¹ ∂tar/∂θ,
    which is the implicit function theorem's dp/dθ, so the gradient of the map is exact.

    Why not freeze p (differentiate through ∂S/∂p only)? Measured against finite differences of
    ``bisection_step`` that gradient is wrong even in sign: a change of S moves tar and sou
    alike, and the frozen-p gradient keeps the part that the Newton solve cancels.
    mu, p: (B, n) → (B, n).
    """
    t = torch.full((mu.shape[0],), float(h), dtype=mu.dtype, device=mu.device)
    pv = p.detach().requires_grad_(True)
    f, jac = newton_system(s_fn, s_fn.chart, t, pv, mu)
    with torch.enable_grad():
        # pv is a leaf: the backward pass only leaves a (discarded) pv.grad behind.
        pt = pv - torch.linalg.solve(jac, f[..., None])[..., 0]
        (xt,) = torch.autograd.grad(s_fn(t, pt).sum(), pt, create_graph=True)
        return sou(s_fn.chart, xt, pt, algebra=s_fn.algebra)


def step_map(s_fn: GeneratingFunction, mu: Tensor, h: float) -> tuple[Tensor, Tensor]:
    """The model's bisection step μ_k ↦ μ_{k+1} = sou(∂S/∂p(h, p), p) with tar(∂S/∂p(h, p), p) =
    μ_k, differentiable in the weights (exactly, see ``_differentiable_step``); the Newton solve
    itself is not tracked. mu (B, n) → (μ_{k+1} (B, n), NaN where not converged; converged (B,))."""
    p, ok = solve_momentum(s_fn, mu, h, max_iter=_DATA_NEWTON_ITERATIONS)
    out = _differentiable_step(s_fn, mu, torch.where(ok[:, None], p, mu), h)
    return torch.where(ok[:, None], out, torch.full_like(out, float("nan"))), ok


def data_loss(s_fn: GeneratingFunction, mu_k: Tensor, mu_k1: Tensor, h: float) -> Tensor:
    """Mean of |step_map(μ_k) − μ_{k+1}|² / |μ_k|² (squared relative one-step error, scale-free
    like the homogeneous HJ loss) over the pairs whose Newton solve converged; (m, n) each → ()."""
    p, ok = solve_momentum(s_fn, mu_k, h, max_iter=_DATA_NEWTON_ITERATIONS)
    # Failed solves are dropped before the differentiable part: masking their NaNs afterwards
    # would still send 0·NaN = NaN into every weight's gradient.
    mu_k, mu_k1, p = mu_k[ok], mu_k1[ok], p[ok]
    out = _differentiable_step(s_fn, mu_k, p, h)
    err = ((out - mu_k1) ** 2).sum(1) / (mu_k * mu_k).sum(1).clamp_min(1e-300)
    return err.sum() / max(len(err), 1)


@dataclass
class TrainResult:
    model: GeneratingFunction
    config: TrainConfig
    losses: list[float] = field(default_factory=list)
    """Training loss every ``log_every`` iterations."""
    seconds: float = 0.0
    validation_rms: float = float("nan")
    """Root of the training loss on 8192 held-out points uniform over the domain (seed + 7919)."""
    iterations_run: int = 0
    """Adam iterations actually taken (fewer than ``config.iterations`` after an early stop)."""
    stopped_early: bool = False
    """True when ``train(stop=...)`` asked to stop before the last iteration, or
    ``max_seconds`` ran out (``timed_out``)."""
    lbfgs_losses: list[float] = field(default_factory=list)
    """HJ loss (absolute units) at every L-BFGS loss evaluation, line-search trials included."""
    lbfgs_iterations_run: int = 0
    """L-BFGS iterations actually taken (fewer than asked once it converges)."""
    data_rms: float = float("nan")
    """Root of the data loss (relative one-step error) on the training pairs; NaN without data."""
    baseline_rms: float = float("nan")
    """``validation_rms`` of the exact Taylor terms alone (the network's output set to zero):
    what training has to improve on."""
    timed_out: bool = False
    """True when ``train(max_seconds=...)`` ended the run before its last iteration."""

    @property
    def final_loss(self) -> float:
        """The last training loss evaluated (absolute units): L-BFGS's when it polished, else
        Adam's; NaN when no iteration ran."""
        losses = self.lbfgs_losses or self.losses
        return losses[-1] if losses else float("nan")


def _save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write_bytes(path, buf.getvalue())


#: Largest checkpoint file read back (the paper preset's model and Adam state take ~6 MB).
_MAX_CHECKPOINT_BYTES = 1 << 30


def _load_checkpoint(path: Path) -> dict[str, Any]:
    """A checkpoint read with ``weights_only=True``: tensors, dicts, lists, numbers and strings
    only, so a crafted file cannot run code. Every entry is checked for its type (a model and
    optimizer state of tensors, a byte-tensor generator state, a non-negative iteration, a list
    of finite losses, a finite number of seconds); any problem raises one
    :class:`~poisson_rs.untrusted.InputError` (ValueError) naming the file and the entry."""
    check_input_file(path, max_bytes=_MAX_CHECKPOINT_BYTES, what="checkpoint")
    source = f"checkpoint {path}"
    with parsing(source):
        try:
            state = torch.load(path, weights_only=True, map_location="cpu")
        except Exception as e:  # UnpicklingError, RuntimeError (bad zip), EOFError, ...
            why = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise ValueError(f"not a readable training checkpoint: {why}") from None
        keys = ("config", "model", "optimizer", "generator", "iteration", "losses", "seconds")
        if not isinstance(state, dict) or any(k not in state for k in keys):
            raise ValueError(f"checkpoint {path} lacks the entries {', '.join(keys)}")
    with parsing(source, "iteration"):
        if not _is_int(state["iteration"]) or state["iteration"] < 0:
            raise ValueError(f"checkpoint {path} holds a bad iteration {state['iteration']!r}")
    with parsing(source, "config"):
        if not isinstance(state["config"], dict):
            raise TypeError(f"must be a dict, got {type(state['config']).__name__}")
    with parsing(source, "model"):
        model = state["model"]
        if not isinstance(model, dict) or not all(
            isinstance(k, str) and isinstance(v, Tensor) for k, v in model.items()
        ):
            raise TypeError("must map parameter names to tensors")
    with parsing(source, "optimizer"):
        opt = state["optimizer"]
        if not (
            isinstance(opt, dict)
            and isinstance(opt.get("state"), dict)
            and isinstance(opt.get("param_groups"), list)
        ):
            raise TypeError("must be an optimizer state (a dict with 'state' and 'param_groups')")
    with parsing(source, "generator"):
        gen = state["generator"]
        if not (isinstance(gen, Tensor) and gen.dtype == torch.uint8 and gen.dim() == 1):
            raise TypeError("must be a generator state (a 1-D uint8 tensor)")
    with parsing(source, "losses"):
        losses = state["losses"]
        if not isinstance(losses, list) or not all(isinstance(v, float) for v in losses):
            raise TypeError("must be a list of floats")
    with parsing(source, "seconds"):
        sec = state["seconds"]
        if isinstance(sec, bool) or not isinstance(sec, (int, float)) or not 0 <= sec < math.inf:
            raise ValueError(f"must be a finite number >= 0, got {sec!r}")
    return state


def _check_train_options(checkpoint_every: Any, log_every: Any, max_seconds: Any) -> None:
    """ValueError unless checkpoint_every is an integer >= 1 (and see
    :func:`~poisson_rs.fit.check_run_options`)."""
    if not _is_int(checkpoint_every) or checkpoint_every < 1:
        raise ValueError(f"checkpoint_every must be an integer >= 1, got {checkpoint_every!r}")
    check_run_options(log_every, max_seconds)


def _zero_output(s_fn: GeneratingFunction) -> None:
    """Sets the last layer's weight and bias to zero: the network adds nothing, S is the series."""
    if s_fn.n_parameters():
        with torch.no_grad():
            s_fn.linears[-1].weight.zero_()
            s_fn.linears[-1].bias.zero_()


def _baseline_rms(s_fn: GeneratingFunction, cfg: TrainConfig, t: Tensor, p: Tensor) -> float:
    """Root of the HJ loss at (t, p) of the same Taylor terms without the network."""
    bare = copy.deepcopy(s_fn)
    _zero_output(bare)
    return float(_loss(bare, cfg, t, p, create_graph=False).detach().sqrt())


def baseline_rms(cfg: TrainConfig) -> float:
    """``TrainResult.baseline_rms`` before training: the validation RMS HJ residual of the
    configuration's exact Taylor terms without the network (0 terms: S = 0)."""
    cfg.validate()
    dtype = getattr(torch, cfg.dtype)
    vgen = torch.Generator().manual_seed(cfg.seed + VALIDATION_SEED)
    tv, pv = _sample_domain(cfg, VALIDATION_POINTS, vgen, dtype, cfg.device)
    return _baseline_rms(build_model(cfg), cfg, tv, pv)


def train(
    cfg: TrainConfig,
    *,
    checkpoint: str | Path | None = None,
    checkpoint_every: int = 500,
    resume: bool = False,
    progress: bool = True,
    log_every: int = 10,
    callback: Callable[[int, float], None] | None = None,
    evaluate_every: int = 0,
    stop: Callable[[int, GeneratingFunction], bool] | None = None,
    data: tuple[np.ndarray, np.ndarray] | None = None,
    max_seconds: float | None = None,
    threads: int | None = None,
) -> TrainResult:
    """Trains a generating function on the HJ residual with Adam, then L-BFGS if
    ``cfg.lbfgs_iterations`` > 0.

    ``data = (mu_k, mu_k1)``, two (n, 3) arrays of pairs one step of ``cfg.data_h`` apart, adds
    the data term (weight ``cfg.data_weight``) with the caller's pairs instead of
    ``cfg.data_points`` exact ones; they are not part of the recorded configuration.

    ``checkpoint`` saves the run every ``checkpoint_every`` iterations (atomically);
    ``resume=True`` continues from it, bit-for-bit as if never interrupted on the same device.

    ``stop(iterations_done, model)`` is called every ``evaluate_every`` iterations and after the
    last one; returning True ends training there (e.g. once a rollout of the current model meets
    an accuracy target, see :mod:`poisson_rs.scenes`). ``model`` is the live module, in the
    training dtype and device: export it (:func:`export_bytes`) rather than keep it. Without
    ``stop`` the run is exactly the plain one; an early stop also skips L-BFGS.

    Checkpoints cover the Adam phase; resuming re-runs L-BFGS from the final Adam state.

    ``max_seconds`` ends Adam cleanly once that much wall time has passed (``timed_out``; no
    L-BFGS then); the result is the model at that point. With ``cfg.init = "zero"`` the network
    starts at zero output, so training starts from the Taylor terms, whose residual is reported
    as ``baseline_rms``. Raises ValueError when the loss is not finite at the start (a
    domain too large for the dtype).

    ``threads``: torch threads for the run (1..``max_threads()``); None applies the same policy
    as the command line (:func:`default_threads`: 1 on a machine with at most 2 cores). The
    previous setting is restored afterwards.
    """
    if not isinstance(cfg, TrainConfig):
        # A realization's configuration (log-canonical, polynomial bivector): its own loop.
        return _train_log_canonical(
            cfg,
            checkpoint=checkpoint,
            resume=resume,
            progress=progress,
            log_every=log_every,
            callback=callback,
            stop=stop,
            data=data,
            max_seconds=max_seconds,
            threads=threads,
        )
    cfg.validate()
    _check_train_options(checkpoint_every, log_every, max_seconds)
    n_threads = resolve_threads(threads)
    if checkpoint is not None:
        # Before any work: a checkpoint that cannot be written (a name too long for the file
        # system with the temporary suffix, a read-only folder) would fail only at its first
        # save, so its real write path is tried now.
        probe_writable(checkpoint)
    previous = torch.get_num_threads()
    torch.set_num_threads(n_threads)
    try:
        return _train(
            cfg,
            checkpoint=checkpoint,
            checkpoint_every=checkpoint_every,
            resume=resume,
            progress=progress,
            log_every=log_every,
            callback=callback,
            evaluate_every=evaluate_every,
            stop=stop,
            data=data,
            max_seconds=max_seconds,
        )
    finally:
        torch.set_num_threads(previous)


def _train_log_canonical(
    cfg: Any,
    *,
    checkpoint: str | Path | None,
    resume: bool,
    progress: bool,
    log_every: int,
    callback: Callable[[int, float], None] | None,
    stop: Callable[[int, GeneratingFunction], bool] | None,
    data: tuple[np.ndarray, np.ndarray] | None,
    max_seconds: float | None,
    threads: int | None,
) -> Any:
    """:func:`train` for a log-canonical configuration: the HJ loss alone, with the package's
    thread policy (:func:`~poisson_rs.realizations.log_canonical_hj.train_log_canonical`), and
    the same for a polynomial-realization one
    (:func:`~poisson_rs.realizations.polynomial_hj.train_polynomial`). Checkpoints, data terms
    and early stops are Lie–Poisson features: asking for one is a ValueError naming it."""
    trainer = cfg.run_training
    kind = type(cfg).__name__

    unsupported = {
        "checkpoint": checkpoint is not None,
        "resume": resume,
        "stop": stop is not None,
        "data": data is not None,
    }
    for name, given in unsupported.items():
        if given:
            raise ValueError(
                f"train(): {name} is not supported for a {kind} configuration "
                f"({kind} trains on the HJ residual alone)"
            )
    n_threads = resolve_threads(threads)
    previous = torch.get_num_threads()
    torch.set_num_threads(n_threads)
    try:
        return trainer(
            progress=progress,
            log_every=log_every,
            callback=callback,
            max_seconds=max_seconds,
        )
    finally:
        torch.set_num_threads(previous)


def _train(
    cfg: TrainConfig,
    *,
    checkpoint: str | Path | None,
    checkpoint_every: int,
    resume: bool,
    progress: bool,
    log_every: int,
    callback: Callable[[int, float], None] | None,
    evaluate_every: int,
    stop: Callable[[int, GeneratingFunction], bool] | None,
    data: tuple[np.ndarray, np.ndarray] | None,
    max_seconds: float | None,
) -> TrainResult:
    """:func:`train` after its checks, with the threads set."""
    if stop is not None and (
        isinstance(evaluate_every, bool)
        or not isinstance(evaluate_every, int)
        or evaluate_every < 1
    ):
        raise ValueError(f"evaluate_every must be an integer >= 1, got {evaluate_every!r}")
    dtype = getattr(torch, cfg.dtype)
    pairs = _data_pairs(cfg, data, dtype)
    s_fn = build_model(cfg)
    if cfg.init == "zero":
        _zero_output(s_fn)
    opt = torch.optim.Adam(s_fn.mlp.parameters(), lr=cfg.lr)
    # Adam divides by sqrt(v) + eps with eps = 1e-8: when exact Taylor terms leave a residual of
    # 1e-5, raw gradients sit below eps and training stalls. Optimise the loss relative to its
    # value at initialisation, a function of the configuration alone (so resuming reproduces
    # it); reported losses stay in absolute units.
    pgen = torch.Generator().manual_seed(cfg.seed + SCALE_SEED)
    tp, pp = sample_points(cfg, min(cfg.batch, SCALE_POINTS), pgen, dtype, cfg.device)
    loss_scale = float(_loss(s_fn, cfg, tp, pp, create_graph=False).detach())
    if not math.isfinite(loss_scale):
        raise ValueError(
            f"the HJ loss is {loss_scale} before training: the domain (r_max/half_width, h_max = "
            f"{cfg.h_max}) is too large for {cfg.dtype}"
        )
    if not loss_scale > 0:
        loss_scale = 1.0
    h_data = cfg.resolved_data_h()
    data_scale = 1.0
    if pairs is not None:
        # The data term is normalised the same way, so data_weight = 1 weighs both terms equally
        # at the start whatever their units.
        data_scale = float(data_loss(s_fn, *pairs, h_data).detach())
        if not (math.isfinite(data_scale) and data_scale > 0):
            data_scale = 1.0

    def objective(t: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        """(normalised training loss, absolute HJ loss) at the points (t, p)."""
        loss = _loss(s_fn, cfg, t, p, create_graph=True)
        total = loss / loss_scale
        if pairs is not None:
            total = total + cfg.data_weight * data_loss(s_fn, *pairs, h_data) / data_scale
        return total, loss

    gen = torch.Generator().manual_seed(cfg.seed)
    pool = sample_points(cfg, cfg.n_points, gen, dtype, cfg.device) if cfg.n_points else None
    start, losses, elapsed = 0, [], 0.0
    ckpt = Path(checkpoint) if checkpoint else None
    if resume:
        if ckpt is None or not ckpt.exists():
            raise FileNotFoundError(f"no checkpoint to resume from at {ckpt}")
        state = _load_checkpoint(ckpt)
        if state["config"] != dataclasses.asdict(cfg):
            raise ValueError("the checkpoint was written by a different configuration")
        # Shapes and contents are checked by torch as they load: a mismatch is one error naming
        # the entry, never a traceback from inside torch.
        with parsing(f"checkpoint {ckpt}", "model"):
            s_fn.load_state_dict(state["model"])
            if not all(torch.isfinite(v).all() for v in s_fn.state_dict().values()):
                raise ValueError("holds NaN or infinite weights")
        with parsing(f"checkpoint {ckpt}", "optimizer"):
            opt.load_state_dict(state["optimizer"])
            for param, moments in opt.state.items():
                for key, value in moments.items():
                    if key != "step" and (
                        not isinstance(value, Tensor) or value.shape != param.shape
                    ):
                        raise ValueError(f"Adam's {key!r} does not fit its parameter")
        with parsing(f"checkpoint {ckpt}", "generator"):
            gen.set_state(state["generator"])
        with parsing(f"checkpoint {ckpt}", "iteration"):
            if state["iteration"] > cfg.iterations:
                raise ValueError(
                    f"{state['iteration']} is past the configuration's {cfg.iterations}"
                )
        start, losses, elapsed = state["iteration"], state["losses"], state["seconds"]

    def step_objective(i: int) -> tuple[Tensor, Tensor]:
        if pool is None:
            t, p = sample_points(cfg, cfg.batch, gen, dtype, cfg.device)
        elif cfg.batch >= len(pool[0]):
            t, p = pool
        else:
            idx = torch.randint(len(pool[0]), (cfg.batch,), generator=gen).to(cfg.device)
            t, p = pool[0][idx], pool[1][idx]
        return objective(t, p)

    def save(i: int, run: AdamRun) -> None:
        if ckpt is not None and (i + 1) % checkpoint_every == 0:
            _save_checkpoint(
                ckpt,
                {
                    "config": dataclasses.asdict(cfg),
                    "model": s_fn.state_dict(),
                    "optimizer": opt.state_dict(),
                    "generator": gen.get_state(),
                    "iteration": i + 1,
                    "losses": run.losses,
                    "seconds": time.perf_counter() - run.t0,
                },
            )

    def should_stop(done: int) -> bool:
        # No gradients and no random draws: a run whose stop never fires takes exactly the
        # same steps as one without it.
        if stop is None or not (done % evaluate_every == 0 or done == cfg.iterations):
            return False
        with torch.no_grad():
            return stop(done, s_fn)

    run = adam_loop(
        cfg,
        opt,
        step_objective,
        start=start,
        losses=losses,
        elapsed=elapsed,
        progress=progress,
        log_every=log_every,
        callback=callback,
        max_seconds=max_seconds,
        after_step=save if ckpt is not None else None,
        stop=should_stop if stop is not None else None,
    )
    losses, done, stopped_early, timed_out = run.losses, run.done, run.stopped_early, run.timed_out
    lbfgs_losses: list[float] = []
    lbfgs_done = 0
    if cfg.lbfgs_iterations and s_fn.n_parameters() and not stopped_early:
        lbfgs_done = _polish(s_fn, cfg, objective, dtype, lbfgs_losses)
    seconds = time.perf_counter() - run.t0
    vgen = torch.Generator().manual_seed(cfg.seed + VALIDATION_SEED)
    # Uniform over the domain whatever the sampling, so the residual compares across runs.
    tv, pv = _sample_domain(cfg, VALIDATION_POINTS, vgen, dtype, cfg.device)
    rms = float(_loss(s_fn, cfg, tv, pv, create_graph=False).detach().sqrt())
    baseline = _baseline_rms(s_fn, cfg, tv, pv)
    drms = (
        float(data_loss(s_fn, *pairs, h_data).detach().sqrt())
        if pairs is not None
        else float("nan")
    )
    return TrainResult(
        s_fn.double().cpu(),
        cfg,
        losses,
        seconds,
        rms,
        done,
        stopped_early,
        lbfgs_losses,
        lbfgs_done,
        drms,
        baseline,
        timed_out,
    )


def _data_pairs(
    cfg: TrainConfig, data: tuple[np.ndarray, np.ndarray] | None, dtype: torch.dtype
) -> tuple[Tensor, Tensor] | None:
    """The data term's pairs as tensors (m, n) each, or None when it is off."""
    if data is not None and cfg.data_points:
        raise ValueError("pass data=(mu_k, mu_k1) or set data_points, not both")
    if data is None and not cfg.data_points:
        if cfg.data_weight > 0:
            raise ValueError("data_weight > 0 needs data_points > 0 or train(data=...)")
        return None
    if data is None:
        # Own seed: the data states are independent of the training and validation points.
        gen = torch.Generator().manual_seed(cfg.seed + 15485863)
        _, states = sample_points(cfg, cfg.data_points, gen, torch.float64, "cpu")
        data = data_from_exact(cfg.lie_system(), states.numpy(), cfg.resolved_data_h())
    if cfg.data_weight == 0:
        raise ValueError("data given but data_weight = 0 (the pairs would be unused)")
    mu_k, mu_k1 = (np.asarray(a, dtype=np.float64) for a in data)
    dim = cfg.lie_system().dim
    if mu_k.ndim != 2 or mu_k.shape[1:] != (dim,) or mu_k.shape != mu_k1.shape or not len(mu_k):
        raise ValueError(f"data must be two (n, {dim}) arrays, got {mu_k.shape} and {mu_k1.shape}")
    if not (np.isfinite(mu_k).all() and np.isfinite(mu_k1).all()):
        raise ValueError("data contains NaN or inf")
    return (
        torch.as_tensor(mu_k, dtype=dtype, device=cfg.device),
        torch.as_tensor(mu_k1, dtype=dtype, device=cfg.device),
    )


def _polish(
    s_fn: GeneratingFunction,
    cfg: TrainConfig,
    objective: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]],
    dtype: torch.dtype,
    record: list[float],
) -> int:
    """:func:`~poisson_rs.fit.lbfgs_polish` on one fixed seeded batch of ``batch`` points;
    appends the HJ loss at each evaluation to ``record`` and returns the iterations taken."""
    gen = torch.Generator().manual_seed(cfg.seed + POLISH_SEED)
    t, p = sample_points(cfg, cfg.polish_batch(), gen, dtype, cfg.device)
    return lbfgs_polish(
        list(s_fn.mlp.parameters()),
        lambda: objective(t, p),
        cfg.lbfgs_iterations,
        start=float(objective(t, p)[0].detach()),
        record=record,
    )


def export_bytes(
    s_fn: GeneratingFunction, cfg: TrainConfig, record: Mapping[str, Any] | None = None
) -> bytes:
    """The model file of ``s_fn`` (any dtype or device; written as float64) as bytes, ready for
    ``BisectionIntegrator(bytes)``: how a model is rolled out in Rust in the middle of training."""
    return model_bytes(
        powers=s_fn.powers.cpu().numpy(),
        coeffs=s_fn.coeffs.detach().to(torch.float64).cpu().numpy(),
        layers=s_fn.exported_layers(),
        mlp_power=s_fn.mlp_power,
        mlp_inputs=s_fn.inputs,
        chart=s_fn.chart,
        system=cfg.lie_system(),
        h_max=cfg.h_max,
        domain=cfg.domain_dict(),
        taylor_order=cfg.taylor_order,
        record=record,
    )


def save_result(
    result: TrainResult,
    path: str | Path,
    *,
    name: str,
    command: str,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Exports a trained model with its provenance (command, seed, loss, time); ``extra`` adds
    metadata entries (non-strings stored as JSON), e.g. a scene's target and measured numbers."""
    cfg = result.config
    return save_model(
        result.model,
        path,
        system=cfg.lie_system(),
        h_max=cfg.h_max,
        domain=cfg.domain_dict(),
        taylor_order=cfg.taylor_order,
        record={
            "name": name,
            "command": command,
            "seed": cfg.seed,
            "final_loss": result.final_loss,
            "validation_rms_residual": result.validation_rms,
            "train_seconds": round(result.seconds, 2),
            "iterations": cfg.iterations,
            "config": json.dumps(dataclasses.asdict(cfg)),
            **(dict(extra) if extra else {}),
        },
    )
