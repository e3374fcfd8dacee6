"""Rollouts in torch on a device: ``integrate(..., device="cuda")`` and :func:`on_device`.

A stepper that can step a batch of states in torch has ``torch_step(mu, h)`` ((B, n) tensor →
(B, n) on mu's device): RK4 on every structure whose vector field takes tensors (Lie–Poisson,
log-canonical, expression Hamiltonians), Taylor-HJ and the learned models on Lie–Poisson systems
(autograd Newton), Taylor-HJ on log-canonical systems. :func:`on_device` wraps one as a stepper
that :func:`~poisson_rs.integrate` drives like any other: the same checks, warnings and
failure report, the trajectory copied back as float64.

On CUDA a step is compiled by ``torch.compile`` where it is one graph (RK4: the whole step
fuses into one generated kernel, one thread per trajectory); Newton steps run eagerly, batched.
The same torch code runs on the CPU (``device="cpu"``): that is the reference path the tests
hold against the Rust core, where no GPU is.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from . import devices

#: The state dtypes on the device, by name.
DTYPES = ("float64", "float32")


def check_device(device: Any) -> Any:
    """``device`` as a ``torch.device`` ("cpu", "cuda", "cuda:1", or a torch.device): ValueError
    naming 'device' for anything else, and for CUDA where torch sees none (before any work)."""
    return devices.check_device(
        device,
        instead="use device='cpu' (the torch reference path) or leave device unset (the Rust core)",
    )


class DeviceStepper:
    """``stepper`` run in torch on ``device``: a :class:`~poisson_rs.Stepper` for
    :func:`~poisson_rs.integrate`. Build one with :func:`on_device`.

    ``dtype``: the states' dtype on the device ("float64" or "float32"; a Newton step computes
    in float64 whatever it is given); ``compile``: torch.compile the step (default: on CUDA,
    for a stepper whose step is one graph, ``torch_graph``). Records are copied back to the
    host as float64. A trajectory whose state turns non-finite failed there (code 3) and stays
    NaN.
    """

    def __init__(
        self,
        stepper: Any,
        device: Any = "cuda",
        *,
        dtype: str = "float64",
        compile: bool | None = None,
    ) -> None:
        import torch

        step = getattr(stepper, "torch_step", None)
        if not callable(step):
            raise TypeError(
                f"{_name(stepper)} has no torch step (torch_step): the device rollouts run "
                "RK4 (pr.classical(system, 'rk4')), Taylor-HJ and learned Lie–Poisson "
                "integrators and log-canonical Taylor-HJ"
            )
        if dtype not in DTYPES:
            raise ValueError(f"dtype must be one of {', '.join(DTYPES)}, got {dtype!r}")
        if compile is not None and not isinstance(compile, bool):
            raise TypeError(f"compile must be True, False or None, got {compile!r}")
        self.device = check_device(device)
        dim = int(stepper.dim)
        # Refused here, before any work, if the method has no torch step: a call on no states.
        step(torch.zeros((0, dim), dtype=torch.float64), getattr(stepper, "step_h", None) or 1.0)
        self.stepper = stepper
        self.dtype = dtype
        graph = bool(getattr(stepper, "torch_graph", False))
        self.compile = (self.device.type == "cuda" and graph) if compile is None else compile
        self._dim = dim
        self._compiled: dict[float, Any] = {}

    @property
    def dim(self) -> int:
        return self._dim

    @property
    def name(self) -> str:
        return f"{_name(self.stepper)} on {self.device}"

    def __getattr__(self, key: str) -> Any:
        # What the tools read from a stepper (system, order, poisson, h_max, step_h, domain)
        # is the wrapped stepper's.
        if key in ("system", "order", "poisson", "h_max", "step_h", "domain"):
            return getattr(self.__dict__["stepper"], key)
        raise AttributeError(key)

    def __reduce__(self) -> tuple[Any, ...]:
        return (_restore, (self.stepper, str(self.device), self.dtype, self.compile))

    def _advance(self, h: float) -> Any:
        """One step at h with its failure bookkeeping, ``(x, failed, k) → (x, failed)``:
        compiled once per h where asked, so that a step is one fused kernel on the device. A
        state that turned non-finite is NaN from then on (as the core's rollouts leave it),
        and ``failed`` (int64, −1: none) keeps the first step k at which it did."""
        import torch

        inner = self.stepper.torch_step
        dtype = getattr(torch, self.dtype)

        def advance(x: Any, failed: Any, k: Any) -> tuple[Any, Any]:
            x = inner(x, h).to(dtype)
            bad = ~torch.isfinite(x).all(-1)
            failed = torch.where(bad & (failed < 0), k, failed)
            return torch.where(bad[:, None], math.nan, x), failed

        if not self.compile:
            return advance
        if h not in self._compiled:
            self._compiled[h] = torch.compile(advance, dynamic=False)
        return self._compiled[h]

    def rollout(
        self, x0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The :class:`~poisson_rs.Stepper` contract: x0 (n, dim) checked by integrate."""
        import torch

        dtype = getattr(torch, self.dtype)
        advance = self._advance(float(h))
        n = len(x0)
        records = n_steps // every + 1
        x = torch.as_tensor(np.asarray(x0), dtype=dtype).to(self.device)
        out = torch.empty((records, n, self._dim), dtype=dtype, device=self.device)
        out[0] = x
        failed = torch.full((n,), -1, dtype=torch.int64, device=self.device)
        # The step index as a device tensor: a Python int would be a new constant (and a new
        # compilation) at every step.
        k = torch.zeros((), dtype=torch.int64, device=self.device)
        for step in range(1, n_steps + 1):
            x, failed = advance(x, failed, k)
            k += 1
            if step % every == 0:
                out[step // every] = x
        traj = out.transpose(0, 1).to("cpu", torch.float64).numpy()
        failed_np = failed.cpu().numpy()
        info = {
            "converged": failed_np < 0,
            "failed_step": failed_np,
            "failure_code": np.where(failed_np < 0, 0, 3).astype(np.int64),
        }
        return np.ascontiguousarray(traj), info

    def __repr__(self) -> str:
        return f"DeviceStepper({self.stepper!r}, device={str(self.device)!r}, dtype={self.dtype!r})"


def on_device(
    stepper: Any, device: Any = "cuda", *, dtype: str = "float64", compile: bool | None = None
) -> DeviceStepper:
    """``stepper`` stepping in torch on ``device`` ("cuda", "cuda:N", or "cpu" for the torch
    reference path), for :func:`~poisson_rs.integrate`. TypeError for a stepper without a torch
    step, ValueError for a device torch does not have; both before any work."""
    return DeviceStepper(stepper, device, dtype=dtype, compile=compile)


def _restore(stepper: Any, device: str, dtype: str, compile: bool) -> DeviceStepper:
    return DeviceStepper(stepper, device, dtype=dtype, compile=compile)


def _name(stepper: Any) -> str:
    return str(getattr(stepper, "name", type(stepper).__name__))
