"""Training generating functions as PINNs: minimise the mean squared Hamilton–Jacobi residual

    r(t, p) = ∂S/∂t(t, p) + H(sou(∂S/∂p(t, p), p))

at sampled (t, p), t ∈ [0, h_max] and p in a cube or a spherical shell (the paper's eq. HJML).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .export import model_bytes, save_model
from .generating import MLP_INPUTS, GeneratingFunction
from .groupoid import check_chart, sou
from .taylor import evaluate_terms, taylor_terms


@dataclass
class TrainConfig:
    """Everything that determines a training run (and is recorded in the model file)."""

    inertia: tuple[float, float, float] = (1.5, 2.0, 2.5)
    chart: str = "cayley"
    widths: tuple[int, ...] = (8, 8)
    inputs: str = "homogeneous"
    """What the MLP sees: "t,p" (the paper) or "homogeneous" (see GeneratingFunction)."""
    taylor_order: int = 3
    """Exact Taylor terms S_1..S_K in the polynomial part (0: none, 1: S = −tH + …)."""
    mlp_power: int | None = None
    """m in t^m·MLP; default K + 2 for K ≥ 1 (S_{K+1} vanishes for odd K in the Cayley chart)."""
    domain: str = "shell"
    r_min: float = 1.0
    r_max: float = 4.0
    half_width: float = 3.0
    h_max: float = 0.1
    batch: int = 2048
    n_points: int | None = None
    """Fixed pool of training points (the paper's 80,000); None draws fresh points every step."""
    iterations: int = 2000
    lr: float = 3e-3
    schedule: str = "cosine"
    seed: int = 0
    dtype: str = "float64"
    device: str = "cpu"

    def resolved_mlp_power(self) -> int:
        if self.mlp_power is not None:
            return self.mlp_power
        return 1 if self.taylor_order == 0 else self.taylor_order + 2

    def validate(self) -> None:
        """Raises ValueError naming the first bad setting."""
        check_chart(self.chart)
        if len(self.inertia) != 3 or not all(math.isfinite(i) and i > 0 for i in self.inertia):
            raise ValueError(f"inertia must be 3 positive numbers, got {self.inertia}")
        if self.domain not in ("cube", "shell"):
            raise ValueError(f"domain must be 'cube' or 'shell', got {self.domain!r}")
        if self.domain == "shell" and not 0 <= self.r_min < self.r_max:
            raise ValueError(f"need 0 <= r_min < r_max, got {self.r_min}, {self.r_max}")
        if self.domain == "cube" and not self.half_width > 0:
            raise ValueError(f"half_width must be > 0, got {self.half_width}")
        checks = [
            ("h_max", self.h_max > 0),
            ("batch", self.batch >= 1),
            ("iterations", self.iterations >= 0),
            ("lr", self.lr > 0),
            ("taylor_order", 0 <= self.taylor_order <= 15),
            ("widths", all(w >= 1 for w in self.widths)),
            ("mlp_power", self.resolved_mlp_power() >= 1),
            ("n_points", self.n_points is None or self.n_points >= 1),
        ]
        for name, ok in checks:
            if not ok:
                raise ValueError(f"invalid {name}: {getattr(self, name)!r}")
        if self.inputs not in MLP_INPUTS:
            raise ValueError(f"inputs must be one of {MLP_INPUTS}, got {self.inputs!r}")
        if self.schedule not in ("cosine", "constant"):
            raise ValueError(f"schedule must be 'cosine' or 'constant', got {self.schedule!r}")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be 'float32' or 'float64', got {self.dtype!r}")
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise ValueError("device 'cuda' requested but torch sees no CUDA device")

    def domain_dict(self) -> dict[str, Any]:
        if self.domain == "cube":
            return {"kind": "cube", "half_width": self.half_width, "t_max": self.h_max}
        return {"kind": "shell", "r_min": self.r_min, "r_max": self.r_max, "t_max": self.h_max}


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
    },
}


def hamiltonian(inertia: Sequence[float], mu: Tensor) -> Tensor:
    """H(μ) = ½ Σ μᵢ²/Iᵢ for μ (..., 3) → (...,)."""
    inv = torch.tensor([1.0 / i for i in inertia], dtype=mu.dtype, device=mu.device)
    return 0.5 * (mu * mu * inv).sum(-1)


def sample_points(
    cfg: TrainConfig, n: int, gen: torch.Generator, dtype: torch.dtype, device: str
) -> tuple[Tensor, Tensor]:
    """n training points: t (n,) uniform in [0, h_max] and p (n, 3) uniform in the domain."""
    t = torch.rand(n, generator=gen, dtype=dtype) * cfg.h_max
    if cfg.domain == "cube":
        p = (2.0 * torch.rand(n, 3, generator=gen, dtype=dtype) - 1.0) * cfg.half_width
    else:
        # Uniform in volume: r³ uniform between r_min³ and r_max³.
        d = torch.randn(n, 3, generator=gen, dtype=dtype)
        d = d / d.norm(dim=1, keepdim=True)
        u = torch.rand(n, 1, generator=gen, dtype=dtype)
        r = (cfg.r_min**3 + u * (cfg.r_max**3 - cfg.r_min**3)) ** (1.0 / 3.0)
        p = d * r
    return t.to(device), p.to(device)


def hj_residual(
    s_fn: GeneratingFunction, inertia: Sequence[float], t: Tensor, p: Tensor, create_graph: bool
) -> Tensor:
    """r = ∂S/∂t + H(sou(∂S/∂p, p)) by nested autograd. t (B,), p (B, 3) → (B,).

    For a homogeneous S the residual scales as r(t, λp) = λ² r(λt, p).
    """
    t = t.detach().requires_grad_(True)
    p = p.detach().requires_grad_(True)
    with torch.enable_grad():
        s = s_fn(t, p)
        st, sp = torch.autograd.grad(s.sum(), (t, p), create_graph=create_graph)
        return st + hamiltonian(inertia, sou(s_fn.chart, sp, p))


def build_model(cfg: TrainConfig) -> GeneratingFunction:
    """The untrained generating function of a configuration (seeded Xavier-uniform init).

    Inputs are scaled to O(1); the MLP output is scaled by the RMS of the first Taylor term it
    stands in for, S_m, so that the network starts at the right magnitude.
    """
    dtype = getattr(torch, cfg.dtype)
    m = cfg.resolved_mlp_power()
    powers, coeffs = (
        taylor_terms(cfg.inertia, cfg.taylor_order, cfg.chart)
        if cfg.taylor_order
        else (np.zeros((0, 4), np.int64), np.zeros(0))
    )
    r_scale = cfg.half_width * math.sqrt(3) if cfg.domain == "cube" else cfg.r_max
    homogeneous = cfg.inputs == "homogeneous"
    # Output scale: RMS over the domain of S_m (the term the MLP replaces first), per unit
    # |p|^(m+1) for the homogeneous ansatz.
    gen = torch.Generator().manual_seed(cfg.seed + 1)
    _, p = sample_points(cfg, 2048, gen, torch.float64, "cpu")
    pw, cf = taylor_terms(cfg.inertia, max(m, 1), cfg.chart)
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
        input_scale=(t_scale, p_scale, p_scale, p_scale),
        output_scale=out_scale,
        dtype=dtype,
    ).to(cfg.device)


def _loss(
    s_fn: GeneratingFunction, cfg: TrainConfig, t: Tensor, p: Tensor, create_graph: bool
) -> Tensor:
    """Mean squared HJ residual (eq. HJML); for the homogeneous ansatz each residual is divided by
    |p|², which makes every point weigh as its image on the unit sphere."""
    r = hj_residual(s_fn, cfg.inertia, t, p, create_graph=create_graph)
    if cfg.inputs == "homogeneous":
        r = r / (p * p).sum(1)
    return r.pow(2).mean()


@dataclass
class TrainResult:
    model: GeneratingFunction
    config: TrainConfig
    losses: list[float] = field(default_factory=list)
    """Training loss every ``log_every`` iterations."""
    seconds: float = 0.0
    validation_rms: float = float("nan")
    """Root of the training loss on 8192 held-out points (seed + 7919)."""
    iterations_run: int = 0
    """Adam iterations actually taken (fewer than ``config.iterations`` after an early stop)."""
    stopped_early: bool = False
    """True when ``train(stop=...)`` asked to stop before the last iteration."""


def _save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(state, tmp)
    tmp.replace(path)


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
) -> TrainResult:
    """Trains a generating function on the HJ residual with Adam.

    ``checkpoint`` saves the run every ``checkpoint_every`` iterations (atomically);
    ``resume=True`` continues from it, bit-for-bit as if never interrupted on the same device.

    ``stop(iterations_done, model)`` is called every ``evaluate_every`` iterations and after the
    last one; returning True ends training there (e.g. once a rollout of the current model meets
    an accuracy target, see :mod:`poisson_rs.scenes`). ``model`` is the live module, in the
    training dtype and device: export it (:func:`export_bytes`) rather than keep it. Without
    ``stop`` the run is exactly the plain one.
    """
    cfg.validate()
    if stop is not None and (
        isinstance(evaluate_every, bool)
        or not isinstance(evaluate_every, int)
        or evaluate_every < 1
    ):
        raise ValueError(f"evaluate_every must be an integer >= 1, got {evaluate_every!r}")
    dtype = getattr(torch, cfg.dtype)
    s_fn = build_model(cfg)
    opt = torch.optim.Adam(s_fn.mlp.parameters(), lr=cfg.lr)
    # Adam divides by sqrt(v) + eps with eps = 1e-8: when exact Taylor terms leave a residual of
    # 1e-5, raw gradients sit below eps and training stalls. Optimise the loss relative to its
    # value at initialisation, a function of the configuration alone (so resuming reproduces
    # it); reported losses stay in absolute units.
    pgen = torch.Generator().manual_seed(cfg.seed + 104729)
    tp, pp = sample_points(cfg, min(cfg.batch, 4096), pgen, dtype, cfg.device)
    loss_scale = float(_loss(s_fn, cfg, tp, pp, create_graph=False).detach())
    if not (math.isfinite(loss_scale) and loss_scale > 0):
        loss_scale = 1.0
    lr_at: Callable[[int], float]
    if cfg.schedule == "cosine":
        # Cosine decay to 1% of lr: most of the final accuracy comes from the small-lr tail.
        def lr_at(i: int) -> float:
            return cfg.lr * (
                0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * i / max(cfg.iterations, 1)))
            )
    else:

        def lr_at(i: int) -> float:
            return cfg.lr

    gen = torch.Generator().manual_seed(cfg.seed)
    pool = sample_points(cfg, cfg.n_points, gen, dtype, cfg.device) if cfg.n_points else None
    start, losses, elapsed = 0, [], 0.0
    ckpt = Path(checkpoint) if checkpoint else None
    if resume:
        if ckpt is None or not ckpt.exists():
            raise FileNotFoundError(f"no checkpoint to resume from at {ckpt}")
        state = torch.load(ckpt, weights_only=False)
        if state["config"] != dataclasses.asdict(cfg):
            raise ValueError("the checkpoint was written by a different configuration")
        s_fn.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        gen.set_state(state["generator"])
        start, losses, elapsed = state["iteration"], state["losses"], state["seconds"]
    if s_fn.n_parameters() == 0 or cfg.iterations == 0:
        start = cfg.iterations
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.iterations, initial=start, desc="train", unit="it", leave=True)
    t0 = time.perf_counter() - elapsed
    # A model without parameters skips training (start = iterations above) and took no step.
    done, stopped_early = (start if s_fn.n_parameters() else 0), False
    for i in range(start, cfg.iterations):
        for g in opt.param_groups:
            g["lr"] = lr_at(i)
        if pool is None:
            t, p = sample_points(cfg, cfg.batch, gen, dtype, cfg.device)
        elif cfg.batch >= len(pool[0]):
            t, p = pool
        else:
            idx = torch.randint(len(pool[0]), (cfg.batch,), generator=gen).to(cfg.device)
            t, p = pool[0][idx], pool[1][idx]
        opt.zero_grad(set_to_none=True)
        loss = _loss(s_fn, cfg, t, p, create_graph=True)
        (loss / loss_scale).backward()
        opt.step()
        if i % log_every == 0 or i == cfg.iterations - 1:
            value = float(loss.detach())
            losses.append(value)
            if bar is not None:
                bar.set_postfix(loss=f"{value:.3e}", refresh=False)
            if callback is not None:
                callback(i, value)
        if bar is not None:
            bar.update(1)
        if ckpt is not None and (i + 1) % checkpoint_every == 0:
            _save_checkpoint(
                ckpt,
                {
                    "config": dataclasses.asdict(cfg),
                    "model": s_fn.state_dict(),
                    "optimizer": opt.state_dict(),
                    "generator": gen.get_state(),
                    "iteration": i + 1,
                    "losses": losses,
                    "seconds": time.perf_counter() - t0,
                },
            )
        done = i + 1
        if stop is not None and (done % evaluate_every == 0 or done == cfg.iterations):
            # No gradients and no random draws: a run whose stop never fires takes exactly the
            # same steps as one without it.
            with torch.no_grad():
                if stop(done, s_fn):
                    stopped_early = done < cfg.iterations
                    break
    if bar is not None:
        bar.close()
    seconds = time.perf_counter() - t0
    vgen = torch.Generator().manual_seed(cfg.seed + 7919)
    tv, pv = sample_points(cfg, 8192, vgen, dtype, cfg.device)
    rms = float(_loss(s_fn, cfg, tv, pv, create_graph=False).detach().sqrt())
    return TrainResult(s_fn.double().cpu(), cfg, losses, seconds, rms, done, stopped_early)


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
        inertia=cfg.inertia,
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
        inertia=cfg.inertia,
        h_max=cfg.h_max,
        domain=cfg.domain_dict(),
        taylor_order=cfg.taylor_order,
        record={
            "name": name,
            "command": command,
            "seed": cfg.seed,
            "final_loss": result.losses[-1] if result.losses else float("nan"),
            "validation_rms_residual": result.validation_rms,
            "train_seconds": round(result.seconds, 2),
            "iterations": cfg.iterations,
            "config": json.dumps(dataclasses.asdict(cfg)),
            **(dict(extra) if extra else {}),
        },
    )
