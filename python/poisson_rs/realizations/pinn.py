"""What every realization's learned S shares: the network term t^M · s_out · N((t, x) scaled) with
its export, and the PINN fit (Adam on the mean squared Hamilton–Jacobi residual, then optional
L-BFGS, then the held-out residual against the Taylor terms alone).

A realization module (:mod:`.log_canonical_hj`, :mod:`.polynomial_hj`) supplies its exact Taylor
terms, its HJ residual r(t, x) and its sampler; the loop, the schedule, the progress bar and the
result are here, once.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

#: r(s_fn, t, x, create_graph) → (B,) HJ residual.
Residual = Callable[[torch.nn.Module, Tensor, Tensor, bool], Tensor]
#: sample(n, generator, dtype) → (t (n,), x (n, dim)).
Sampler = Callable[[int, torch.Generator, torch.dtype], tuple[Tensor, Tensor]]


class NetworkTerm(torch.nn.Module):
    """The base of a realization's learned S = Taylor(t, x) + t^M · s_out · N((t, x) scaled):
    the tanh MLP N on ((t, x) − shift) · scale and its export. A subclass adds its Taylor terms
    and ``forward``.

    ``dim`` n; ``widths`` the hidden widths (empty: no network); ``center``, ``half`` (n,) the
    box of x the inputs are scaled from; ``h_max`` the time scale; ``output_scale`` s_out.
    """

    # Buffers, declared so that they type as tensors (not ``nn.Module.__getattr__``'s union).
    input_scale: Tensor
    input_shift: Tensor

    def __init__(
        self,
        dim: int,
        widths: tuple[int, ...],
        center: np.ndarray,
        half: np.ndarray,
        h_max: float,
        output_scale: float = 1.0,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        self.dim = dim
        scale = np.concatenate([[1.0 / h_max], 1.0 / np.asarray(half, np.float64)])
        shift = np.concatenate([[0.0], np.asarray(center, np.float64)])
        self.register_buffer("input_scale", torch.as_tensor(scale, dtype=dtype))
        self.register_buffer("input_shift", torch.as_tensor(shift, dtype=dtype))
        self.output_scale = float(output_scale)
        sizes = [dim + 1, *widths, 1] if widths else []
        self.linears = torch.nn.ModuleList(
            torch.nn.Linear(a, b, dtype=dtype) for a, b in itertools.pairwise(sizes)
        )

    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def layers(self) -> list[torch.nn.Linear]:
        """The MLP's linear layers as such (iterating a ModuleList types them as ``nn.Module``)."""
        return [m for m in self.linears if isinstance(m, torch.nn.Linear)]

    def zero_output_layer(self) -> None:
        """Zeroes the last layer, so that the network starts as N = 0 (S = its Taylor terms)."""
        with torch.no_grad():
            self.layers()[-1].weight.zero_()
            self.layers()[-1].bias.zero_()

    def network(self, t: Tensor, x: Tensor) -> Tensor:
        """N with the input scaling, before t^M and s_out: t (B,), x (B, n) → (B,)."""
        z = (torch.cat([t[:, None], x], 1) - self.input_shift) * self.input_scale
        for i, layer in enumerate(self.linears):
            z = layer(z)
            if i + 1 < len(self.linears):
                z = torch.tanh(z)
        return z[:, 0]

    def exported_layers(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(weight (out, in), bias (out,)) float64 pairs with the input shift and scales folded
        in, so that the exported network is s_out · N(t, x) on raw inputs (t, x)."""
        out = []
        scale = self.input_scale.detach().to(torch.float64).cpu().numpy()
        shift = self.input_shift.detach().to(torch.float64).cpu().numpy()
        for i, layer in enumerate(self.layers()):
            w = layer.weight.detach().to(torch.float64).cpu().numpy().copy()
            b = layer.bias.detach().to(torch.float64).cpu().numpy().copy()
            if i == 0:
                w = w * scale[None, :]
                b = b - w @ shift
            if i == len(self.linears) - 1:
                w, b = w * self.output_scale, b * self.output_scale
            out.append((w, b))
        return out


class PinnConfig(Protocol):
    """The fields of a realization's train config the fit reads."""

    seed: int
    iterations: int
    batch: int
    lr: float
    schedule: str
    dtype: str
    lbfgs_iterations: int
    lbfgs_batch: int


@dataclass
class PinnResult:
    """A trained S and how the fit went."""

    model: Any
    config: Any
    losses: list[float] = field(default_factory=list)
    """Mean squared HJ residual every ``log_every`` Adam iterations (units of energy²), then
    once after L-BFGS."""
    seconds: float = 0.0
    validation_rms: float = float("nan")
    """RMS HJ residual on 8192 held-out points of the box (seed + 7919)."""
    baseline_rms: float = float("nan")
    """The same for the Taylor terms alone (the network's output zero)."""
    iterations_run: int = 0
    timed_out: bool = False
    lbfgs_iterations_run: int = 0

    @property
    def final_loss(self) -> float:
        return self.losses[-1] if self.losses else float("nan")


def is_int(v: Any) -> bool:
    """An integer that is not a bool (NumPy integers included)."""
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def check_run_options(log_every: Any, max_seconds: Any) -> None:
    """ValueError naming ``log_every`` (an integer ≥ 1) or ``max_seconds`` (None or > 0)."""
    if not is_int(log_every) or log_every < 1:
        raise ValueError(f"log_every must be an integer >= 1, got {log_every!r}")
    if max_seconds is not None and not (
        isinstance(max_seconds, (int, float))
        and not isinstance(max_seconds, bool)
        and max_seconds > 0
    ):
        raise ValueError(f"max_seconds must be a number > 0, got {max_seconds!r}")


def box_points(
    box: tuple[np.ndarray, np.ndarray],
    h_max: float,
    n: int,
    gen: torch.Generator,
    dtype: torch.dtype,
) -> tuple[Tensor, Tensor]:
    """n training points: t (n,) uniform in [0, h_max] and (n, dim) coordinates uniform in the
    box (center, half width), t drawn first from ``gen`` (so a seed gives the same points)."""
    center, half = (torch.as_tensor(a, dtype=dtype) for a in box)
    t = torch.rand(n, generator=gen, dtype=dtype) * h_max
    u = 2.0 * torch.rand(n, len(center), generator=gen, dtype=dtype) - 1.0
    return t, center + half * u


def fit(
    cfg: PinnConfig,
    s_fn: torch.nn.Module,
    bare: Callable[[], torch.nn.Module],
    residual: Residual,
    sample: Sampler,
    *,
    progress: bool = True,
    log_every: int = 10,
    callback: Callable[[int, float], None] | None = None,
    max_seconds: float | None = None,
) -> PinnResult:
    """Trains ``s_fn`` (its parameters: the network) on the mean squared HJ residual with Adam
    (cosine decay to 1 % of lr), the loss taken relative to its value at the start (the Taylor
    terms' residual is small, so raw gradients would sit below Adam's eps), then
    ``cfg.lbfgs_iterations`` of L-BFGS. ``bare()`` builds the same S in float64 without the
    network, for ``baseline_rms``. ``progress`` shows a tqdm bar; ``max_seconds`` ends the run
    cleanly once that much time has passed. Threads are the caller's."""
    check_run_options(log_every, max_seconds)
    dtype = getattr(torch, cfg.dtype)
    n_params = sum(p.numel() for p in s_fn.parameters())
    pgen = torch.Generator().manual_seed(cfg.seed + 104729)
    tp, xp = sample(min(cfg.batch, 4096), pgen, dtype)
    scale = float(residual(s_fn, tp, xp, False).pow(2).mean())
    if not math.isfinite(scale):
        raise ValueError(f"the HJ loss is {scale} before training: the box is too large")
    scale = scale if scale > 0 else 1.0
    opt = torch.optim.Adam(s_fn.parameters(), lr=cfg.lr)

    def lr_at(i: int) -> float:
        if cfg.schedule == "constant":
            return cfg.lr
        return cfg.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * i / max(cfg.iterations, 1))))

    gen = torch.Generator().manual_seed(cfg.seed)
    losses: list[float] = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.iterations, desc="train", unit="it", leave=True)
    t0 = time.perf_counter()
    done, timed_out = 0, False
    for i in range(cfg.iterations if n_params else 0):
        if max_seconds is not None and time.perf_counter() - t0 >= max_seconds:
            timed_out = True
            break
        for g in opt.param_groups:
            g["lr"] = lr_at(i)
        t, x = sample(cfg.batch, gen, dtype)
        opt.zero_grad(set_to_none=True)
        loss = residual(s_fn, t, x, True).pow(2).mean()
        (loss / scale).backward()
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
        done = i + 1
    if bar is not None:
        bar.close()
    lbfgs_done = 0
    if cfg.lbfgs_iterations and n_params and not timed_out:
        lbfgs_done = _polish(cfg, s_fn, residual, sample, dtype, losses)
    seconds = time.perf_counter() - t0
    s_fn = s_fn.double()
    vgen = torch.Generator().manual_seed(cfg.seed + 7919)
    tv, xv = sample(8192, vgen, torch.float64)
    rms = float(residual(s_fn, tv, xv, False).pow(2).mean().sqrt())
    baseline = float(residual(bare(), tv, xv, False).pow(2).mean().sqrt())
    return PinnResult(s_fn, cfg, losses, seconds, rms, baseline, done, timed_out, lbfgs_done)


def _polish(
    cfg: PinnConfig,
    s_fn: torch.nn.Module,
    residual: Residual,
    sample: Sampler,
    dtype: torch.dtype,
    record: list[float],
) -> int:
    """L-BFGS (strong Wolfe) on one fixed seeded batch, the loss relative to its value at the
    start (torch's thresholds are absolute); appends the final HJ loss to ``record`` and returns
    the iterations taken."""
    gen = torch.Generator().manual_seed(cfg.seed + 31337)
    t, x = sample(cfg.lbfgs_batch, gen, dtype)
    start = float(residual(s_fn, t, x, False).pow(2).mean())
    scale = start if math.isfinite(start) and start > 0 else 1.0
    params = list(s_fn.parameters())
    n = cfg.lbfgs_iterations
    opt = torch.optim.LBFGS(
        params,
        lr=1.0,
        max_iter=n,
        max_eval=25 * n,
        tolerance_grad=1e-12,
        tolerance_change=1e-15,
        history_size=50,
        line_search_fn="strong_wolfe",
    )

    def closure() -> Tensor:
        opt.zero_grad(set_to_none=True)
        loss = residual(s_fn, t, x, True).pow(2).mean() / scale
        loss.backward()
        return loss.detach()

    opt.step(closure)
    record.append(float(residual(s_fn, t, x, False).pow(2).mean()))
    return int(opt.state[params[0]].get("n_iter", 0))


def model_file(
    tensors: dict[str, np.ndarray],
    s_fn: NetworkTerm,
    cfg: Any,
    *,
    structure: str,
    system: Any,
    inputs: str,
    fields: dict[str, str] | None = None,
    record: Any = None,
) -> bytes:
    """A learned S's model file: ``tensors`` plus the MLP's (``mlp.{i}.weight``/``.bias`` on
    raw inputs), and the metadata every realization records (``format``, ``structure``,
    ``mlp_power``, ``mlp_inputs``, ``widths``, ``taylor_order``, ``system`` as JSON, ``h_max``,
    ``domain``), then ``fields`` and the ``record`` entries (non-strings as JSON). Refuses NaN
    or infinite weights (a diverged run)."""
    import json

    from ..export import FORMAT, PACKAGE_VERSION, safetensors_bytes

    layers = s_fn.exported_layers()
    if not all(np.isfinite(a).all() for layer in layers for a in layer):
        raise ValueError("the model has NaN or infinite weights (training diverged?)")
    tensors = dict(tensors)
    for i, (w, b) in enumerate(layers):
        tensors[f"mlp.{i}.weight"] = np.ascontiguousarray(w, dtype=np.float64)
        tensors[f"mlp.{i}.bias"] = np.ascontiguousarray(b, dtype=np.float64)
    meta: dict[str, str] = {
        "format": FORMAT,
        "structure": structure,
        "mlp_power": str(s_fn.mlp_power),
        "mlp_inputs": inputs,
        "widths": json.dumps([int(w.shape[0]) for w, _ in layers[:-1]]),
        "taylor_order": str(s_fn.taylor_order),
        **(fields or {}),
        "system": json.dumps(system.to_dict()),
        "h_max": repr(float(cfg.h_max)),
        "domain": json.dumps(cfg.domain_dict()),
        "package_version": PACKAGE_VERSION,
    }
    for k, v in (record or {}).items():
        meta[k] = v if isinstance(v, str) else json.dumps(v, sort_keys=True)
    return safetensors_bytes(tensors, meta)


def provenance(result: PinnResult, *, name: str, command: str, extra: Any = None) -> dict[str, Any]:
    """The training record a saved model carries: its name and command, the seed, the losses
    and residuals, the time and the whole config (JSON), plus ``extra``."""
    import dataclasses
    import json

    cfg = result.config
    return {
        "name": name,
        "command": command,
        "seed": cfg.seed,
        "final_loss": result.final_loss,
        "validation_rms_residual": result.validation_rms,
        "baseline_rms_residual": result.baseline_rms,
        "train_seconds": round(result.seconds, 2),
        "iterations": cfg.iterations,
        "config": json.dumps(dataclasses.asdict(cfg)),
        **(dict(extra) if extra else {}),
    }
