"""What every realization's learned S shares: the network term t^M · s_out · N((t, x) scaled) with
its export, and the PINN fit on the mean squared Hamilton–Jacobi residual through the package's
one training stack (:mod:`poisson_rs.fit`: Adam, then optional L-BFGS), then the held-out
residual against the Taylor terms alone.

A realization module (:mod:`.log_canonical_hj`, :mod:`.polynomial_hj`) supplies its exact Taylor
terms, its HJ residual r(t, x), its sampler and its configuration (a
:class:`~poisson_rs.fit.FitConfig`); the loop, the schedule and the polish are in
:mod:`poisson_rs.fit`.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..fit import (
    POLISH_SEED,
    SCALE_POINTS,
    SCALE_SEED,
    VALIDATION_POINTS,
    VALIDATION_SEED,
    FitConfig,
    adam_loop,
    check_run_options,
    lbfgs_polish,
)

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


#: The configuration a realization trains from: the package's one training configuration type.
PinnConfig = FitConfig


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
    cfg: FitConfig,
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
    """Trains ``s_fn`` (its parameters: the network) on the mean squared HJ residual with the
    package's loop (:func:`~poisson_rs.fit.adam_loop`: Adam, cosine decay to 1 % of lr), the loss
    taken relative to its value at the start (the Taylor terms' residual is small, so raw
    gradients would sit below Adam's eps), then ``cfg.lbfgs_iterations`` of L-BFGS
    (:func:`~poisson_rs.fit.lbfgs_polish`). ``bare()`` builds the same S in float64 without the
    network, for ``baseline_rms``. ``progress`` shows a tqdm bar; ``max_seconds`` ends the run
    cleanly once that much time has passed. Threads are the caller's."""
    check_run_options(log_every, max_seconds)
    dtype = cfg.torch_dtype()
    pgen = torch.Generator().manual_seed(cfg.seed + SCALE_SEED)
    tp, xp = sample(min(cfg.batch, SCALE_POINTS), pgen, dtype)
    scale = float(residual(s_fn, tp, xp, False).pow(2).mean())
    if not math.isfinite(scale):
        raise ValueError(f"the HJ loss is {scale} before training: the box is too large")
    scale = scale if scale > 0 else 1.0
    opt = torch.optim.Adam(s_fn.parameters(), lr=cfg.lr)
    gen = torch.Generator().manual_seed(cfg.seed)

    def objective(i: int) -> tuple[Tensor, Tensor]:
        t, x = sample(cfg.batch, gen, dtype)
        loss = residual(s_fn, t, x, True).pow(2).mean()
        return loss / scale, loss

    run = adam_loop(
        cfg,
        opt,
        objective,
        progress=progress,
        log_every=log_every,
        callback=callback,
        max_seconds=max_seconds,
    )
    losses = run.losses
    lbfgs_done = 0
    n_params = sum(p.numel() for p in s_fn.parameters())
    if cfg.lbfgs_iterations and n_params and not run.timed_out:
        lbfgs_done = _polish(cfg, s_fn, residual, sample, dtype, losses)
    seconds = time.perf_counter() - run.t0
    s_fn = s_fn.double()
    vgen = torch.Generator().manual_seed(cfg.seed + VALIDATION_SEED)
    tv, xv = sample(VALIDATION_POINTS, vgen, torch.float64)
    rms = float(residual(s_fn, tv, xv, False).pow(2).mean().sqrt())
    baseline = float(residual(bare(), tv, xv, False).pow(2).mean().sqrt())
    return PinnResult(
        s_fn, cfg, losses, seconds, rms, baseline, run.done, run.timed_out, lbfgs_done
    )


def _polish(
    cfg: FitConfig,
    s_fn: torch.nn.Module,
    residual: Residual,
    sample: Sampler,
    dtype: torch.dtype,
    record: list[float],
) -> int:
    """:func:`~poisson_rs.fit.lbfgs_polish` on one fixed seeded batch of ``cfg.polish_batch()``
    points; appends the final HJ loss to ``record`` and returns the iterations taken."""
    gen = torch.Generator().manual_seed(cfg.seed + POLISH_SEED)
    t, x = sample(cfg.polish_batch(), gen, dtype)

    def objective() -> tuple[Tensor, Tensor]:
        loss = residual(s_fn, t, x, True).pow(2).mean()
        return loss, loss

    start = float(residual(s_fn, t, x, False).pow(2).mean())
    done = lbfgs_polish(list(s_fn.parameters()), objective, cfg.lbfgs_iterations, start=start)
    record.append(float(residual(s_fn, t, x, False).pow(2).mean()))
    return done


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
