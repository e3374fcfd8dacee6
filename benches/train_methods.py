"""Training throughput (issue 6): seconds per Adam iteration for the ways of getting ∂S/∂t and
∂S/∂p inside the HJ loss r = ∂S/∂t + H(sou(∂S/∂p, p)), measured in one run on one machine.

Methods (each a function ``(s_fn, t, p) -> (∂S/∂t (B,), ∂S/∂p (B, 3))`` differentiable in the
MLP parameters, importable from this file; ``METHODS`` names them):

- ``nested``: nested autograd, ``torch.autograd.grad(..., create_graph=True)`` (the trainer's
  ``derivatives="autograd"``, how the shipped models were trained);
- ``func_grad``: ``torch.func.vmap(torch.func.grad(...))`` of ``functional_call``, per sample;
- ``func_jvp``: ``torch.func.jvp`` of the batched model along the 4 input directions (each S_b
  depends on (t_b, p_b) only, so one batched tangent gives every sample's derivative);
- ``hand``: (value, ∂/∂t, ∂/∂p₁, ∂/∂p₂, ∂/∂p₃) propagated by hand through the tanh layers, plus
  the polynomial's closed-form gradient, so the loss needs only a first-order backward;
- ``hand_reverse``: the same closed forms, but the MLP's input gradient by a hand-written backward
  pass (one cotangent instead of four tangents); autograd differentiates it once more. This is
  ``poisson_rs.generating.hj_derivatives``, what the trainer uses by default;
- ``compiled:<m>``: ``torch.compile`` of method m with the loss (by default the fastest in the
  warm-up; ``--compile M ...`` names others, ``--compile`` alone none), its warm-up bounded by
  ``--compile-timeout`` with SIGALRM; a failure is reported, not raised.

Every method is first checked against ``nested`` on the configuration's own model and points, in
float64 (∂S/∂t, ∂S/∂p to 1e-12 relative, their parameter derivatives to 1e-10), so that a wrong
method is never timed. One iteration = zero_grad, loss, backward, Adam step, as in the trainer,
on pre-sampled batches (sampling is excluded: it is the same for every method). Methods run
round-robin, the order rotated each round, so that load from other jobs hits them alike; the
table reports medians.

Usage: ``python benches/train_methods.py [--repeats 30] [--paper] [--device cuda] [--json F]``.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import logging
import math
import signal
import statistics
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import torch
from torch import Tensor
from torch.func import functional_call, grad, jvp, vmap

from poisson_rs.generating import (
    GeneratingFunction,
    assemble_derivatives,
    first_layer,
    hj_derivatives,
    polynomial_gradient,
)
from poisson_rs.train import (
    PRESETS,
    TrainConfig,
    _loss,
    build_model,
    loss_from_derivatives,
    sample_points,
)

Derivatives = Callable[[GeneratingFunction, Tensor, Tensor], tuple[Tensor, Tensor]]
LossFn = Callable[[Tensor, Tensor], Tensor]

# --------------------------------------------------------------------------------------------
# Ways of computing (∂S/∂t, ∂S/∂p)
# --------------------------------------------------------------------------------------------


def nested_autograd(s_fn: GeneratingFunction, t: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
    """∂S/∂t and ∂S/∂p by reverse mode with ``create_graph=True``:
    ``generating.hj_derivatives(method="autograd")``."""
    return hj_derivatives(s_fn, t, p, method="autograd")


def func_vmap_grad(s_fn: GeneratingFunction, t: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
    """∂S/∂t and ∂S/∂p as ``vmap(grad(S))`` over samples, S a ``functional_call`` of the model."""
    params = dict(s_fn.named_parameters())

    def s_one(params: dict[str, Tensor], t1: Tensor, p1: Tensor) -> Tensor:
        return functional_call(s_fn, params, (t1[None], p1[None]))[0]

    st, sp = vmap(grad(s_one, argnums=(1, 2)), in_dims=(None, 0, 0))(params, t, p)
    return st, sp


def func_jvp(s_fn: GeneratingFunction, t: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
    """∂S/∂t and ∂S/∂p by forward mode: ``vmap`` over the 4 unit tangents of ``jvp(S)``."""
    params = dict(s_fn.named_parameters())
    basis = torch.eye(4, dtype=t.dtype, device=t.device)[:, None, :].expand(4, t.shape[0], 4)

    def s_batch(t: Tensor, p: Tensor) -> Tensor:
        return functional_call(s_fn, params, (t, p))

    def tangent(v: Tensor) -> Tensor:
        return jvp(s_batch, (t, p), (v[:, 0], v[:, 1:]))[1]

    d = vmap(tangent)(basis)  # (4, B): rows ∂/∂t, ∂/∂p₁, ∂/∂p₂, ∂/∂p₃
    return d[0], d[1:].T


def hand_forward(s_fn: GeneratingFunction, t: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
    """∂S/∂t and ∂S/∂p by hand-propagated forward-mode tangents: (value, ∂/∂t, ∂/∂p₁..₃)
    through every layer, so that the loss needs only a first-order backward. The closed forms
    around the MLP are the library's (``generating.first_layer``, ``assemble_derivatives``)."""
    if not s_fn.widths:
        g = polynomial_gradient(s_fn, t, p)
        return g[:, 0], g[:, 1:]
    lin = s_fn.linears
    h, w0, jac = first_layer(s_fn, t, p)
    if jac is None:  # inputs "t,p": the identity, the same for every sample
        jac = torch.eye(4, dtype=t.dtype, device=t.device)[None]
    dh = jac.transpose(0, 1) @ w0.T  # (4, B or 1, H): tangents of the pre-activation
    for layer in lin[1:]:
        a = torch.tanh(h)
        da = (1.0 - a * a) * dh  # tanh' = 1 − tanh²; broadcasts (4, 1, H) up to (4, B, H)
        h = torch.nn.functional.linear(a, layer.weight, layer.bias)
        # One GEMM for the 4 tangents together: (4, B, H) @ (H, H') runs as (4B, H) @ (H, H').
        dh = da @ layer.weight.T
    return assemble_derivatives(s_fn, t, p, h[:, 0], dh[..., 0].T)


def hand_reverse(s_fn: GeneratingFunction, t: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
    """The trainer's default: ``generating.hj_derivatives(method="reverse")``, closed forms and a
    hand-written backward pass to the inputs; autograd then differentiates this graph once."""
    return hj_derivatives(s_fn, t, p, method="reverse")


METHODS: dict[str, Derivatives] = {
    "nested": nested_autograd,
    "func_grad": func_vmap_grad,
    "func_jvp": func_jvp,
    "hand": hand_forward,
    "hand_reverse": hand_reverse,
}

# --------------------------------------------------------------------------------------------
# Loss and checks
# --------------------------------------------------------------------------------------------


def hj_loss(s_fn: GeneratingFunction, inertia: tuple[float, ...], method: Derivatives) -> LossFn:
    """``(t, p) -> loss`` with the derivatives taken by ``method``."""

    def loss(t: Tensor, p: Tensor) -> Tensor:
        return loss_from_derivatives(s_fn, inertia, *method(s_fn, t, p), p)

    return loss


def _rel_err(a: Tensor, b: Tensor) -> float:
    """max |a − b| / max |b| (or absolute where b = 0)."""
    a, b = a.detach(), b.detach()
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-300))


def check_method(
    method: Derivatives,
    s_fn: GeneratingFunction,
    t: Tensor,
    p: Tensor,
    *,
    rtol: float = 1e-12,
    vjp_rtol: float = 1e-10,
) -> dict[str, float]:
    """Relative errors of ``method`` against nested autograd, raising AssertionError above the
    tolerances: ∂S/∂t, ∂S/∂p (``rtol``), and their parameter derivatives (``vjp_rtol``), i.e.
    the gradient of Σ (w·∂S/∂t + v·∂S/∂p) for fixed random w, v, worst parameter tensor.

    Not the loss gradient itself: the loss is a mean of squared residuals r = ∂S/∂t + H that
    cancel to ~1e-9 of ∂S/∂t for accurate Taylor parts, so a 1e-16 change in ∂S/∂t moves its
    gradient by 1e-7 relatively whatever the method; the random functional has no cancellation
    and still checks every mixed derivative ∂²S/∂θ∂(t, p) the loss gradient is built from."""
    st0, sp0 = nested_autograd(s_fn, t, p)
    st, sp = method(s_fn, t, p)
    errs = {"dS/dt": _rel_err(st, st0), "dS/dp": _rel_err(sp, sp0), "d2S/dtheta": 0.0}
    params = list(s_fn.mlp.parameters())
    if params:
        gen = torch.Generator().manual_seed(0)
        w = torch.rand(t.shape[0], 4, generator=gen, dtype=t.dtype).to(t.device) * 2 - 1
        g0 = torch.autograd.grad((w[:, 0] * st0).sum() + (w[:, 1:] * sp0).sum(), params)
        g = torch.autograd.grad((w[:, 0] * st).sum() + (w[:, 1:] * sp).sum(), params)
        errs["d2S/dtheta"] = max(_rel_err(a, b) for a, b in zip(g, g0, strict=True))
    ok = errs["dS/dt"] <= rtol and errs["dS/dp"] <= rtol and errs["d2S/dtheta"] <= vjp_rtol
    assert ok, f"{getattr(method, '__name__', method)} disagrees with nested autograd: {errs}"
    return errs


# --------------------------------------------------------------------------------------------
# Timing
# --------------------------------------------------------------------------------------------


class _Deadline(BaseException):
    """Raised by SIGALRM; a BaseException so that torch's ``except Exception`` can't swallow it."""


@contextmanager
def deadline(seconds: float) -> Iterator[None]:
    """Interrupts the block after ``seconds`` with ``_Deadline`` (no-op off the main thread or
    without SIGALRM). Compilation runs in this thread, so an alarm is the one way to bound it."""
    if not hasattr(signal, "SIGALRM") or threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_alarm(signum: int, frame: object) -> None:
        raise _Deadline

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@dataclasses.dataclass
class Runner:
    """One method's own copy of the model, its Adam, and its loss."""

    name: str
    model: GeneratingFunction
    opt: torch.optim.Optimizer
    loss: LossFn
    times: list[float] = dataclasses.field(default_factory=list)

    def step(self, t: Tensor, p: Tensor, loss_scale: float) -> None:
        """One trainer iteration (train.train's loop body without logging)."""
        self.opt.zero_grad(set_to_none=True)
        loss = self.loss(t, p)
        (loss / loss_scale).backward()
        self.opt.step()


def make_runner(
    name: str, base: GeneratingFunction, cfg: TrainConfig, method: Derivatives
) -> Runner:
    model = copy.deepcopy(base)
    opt = torch.optim.Adam(model.mlp.parameters(), lr=cfg.lr)
    return Runner(name, model, opt, hj_loss(model, cfg.inertia, method))


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def timed_step(r: Runner, t: Tensor, p: Tensor, scale: float, device: str) -> float:
    _sync(device)
    t0 = time.perf_counter()
    r.step(t, p, scale)
    _sync(device)
    return time.perf_counter() - t0


def _summary(e: BaseException) -> str:
    """Type and first line of an exception, for the report."""
    lines = str(e).strip().splitlines()
    return f"{type(e).__name__}: {lines[0][:300] if lines else ''}"


def compile_runner(
    base: GeneratingFunction,
    cfg: TrainConfig,
    method_name: str,
    t: Tensor,
    p: Tensor,
    loss_scale: float,
    timeout: float,
) -> tuple[Runner | None, dict[str, Any]]:
    """``torch.compile`` of method ``method_name`` with the loss, warmed up (one forward and
    backward, which compiles both) within ``timeout`` seconds, then checked against nested
    autograd on (t, p) like the eager methods. Returns (runner or None, what happened)."""
    info: dict[str, Any] = {"method": method_name, "ok": False}
    method = METHODS[method_name]
    r = make_runner(f"compiled:{method_name}", base, cfg, method)
    model, inertia = r.model, cfg.inertia

    def loss_parts(t: Tensor, p: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        st, sp = method(model, t, p)
        return loss_from_derivatives(model, inertia, st, sp, p), st, sp

    # Derivatives and loss in one graph: inductor can fuse the tangent arithmetic with the
    # residual's, and AOTAutograd derives one backward for both. The derivatives come out too,
    # for the check; they are (B,) and (B, 3), negligible next to the hidden layers.
    t0 = time.perf_counter()
    # fullgraph=True first, so that a graph break (which can silently leave most of the work
    # eager) is reported; then with breaks allowed. One deadline bounds both attempts.
    for fullgraph in (True, False):
        compiled = torch.compile(loss_parts, fullgraph=fullgraph)
        try:
            with deadline(max(timeout - (time.perf_counter() - t0), 1.0)):
                value = compiled(t, p)[0]
                (value / loss_scale).backward()
                r.opt.zero_grad(set_to_none=True)
                _sync(cfg.device)
        except _Deadline:
            info["error"] = f"warm-up (compilation) exceeded {timeout:g} s; skipped"
            return None, info
        except Exception as e:  # any compile failure is a result to report
            info["fullgraph" if fullgraph else "error"] = _summary(e)
            if fullgraph:
                continue
            return None, info
        if fullgraph:
            info["fullgraph"] = "ok"
        break
    info["compile_seconds"] = time.perf_counter() - t0

    def derivatives(s_fn: GeneratingFunction, t: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        _, st, sp = compiled(t, p)
        return st, sp

    # In the training dtype (compiling a float64 twin would double the compile time); float32
    # gets float32-sized tolerances.
    f64 = t.dtype == torch.float64
    info["check"] = check_method(
        derivatives, model, t, p, rtol=1e-12 if f64 else 1e-5, vjp_rtol=1e-10 if f64 else 1e-3
    )
    r.loss = lambda t, p: compiled(t, p)[0]
    info["ok"] = True
    return r, info


def bench_config(
    cfg: TrainConfig,
    *,
    methods: list[str],
    repeats: int,
    warmup: int,
    n_batches: int,
    compile_methods: list[str],
    compile_timeout: float,
    check_points: int,
) -> dict[str, Any]:
    """Checks, warms up and times every method on one configuration; returns its record."""
    cfg.validate()
    dtype = getattr(torch, cfg.dtype)
    base = build_model(cfg)
    gen = torch.Generator().manual_seed(cfg.seed)
    batches = [sample_points(cfg, cfg.batch, gen, dtype, cfg.device) for _ in range(n_batches)]
    rec: dict[str, Any] = {
        "config": {k: v for k, v in dataclasses.asdict(cfg).items() if k != "inertia"},
        "parameters": base.n_parameters(),
        "checks": {},
    }

    # Correctness first, in float64 on the configuration's own model and points.
    m64 = copy.deepcopy(base).double()
    tc, pc = (x[:check_points].double() for x in batches[0])
    ref = float(_loss(m64, cfg, tc, pc, create_graph=False).detach())
    mine = float(hj_loss(m64, cfg.inertia, nested_autograd)(tc, pc).detach())
    assert math.isclose(ref, mine, rel_tol=1e-12), f"hj_loss {mine} != train._loss {ref}"
    for name in methods:
        rec["checks"][name] = check_method(METHODS[name], m64, tc, pc)
    del m64

    # The trainer's loss normalisation (train.train), so that Adam sees the same numbers.
    t0, p0 = batches[0]
    loss_scale = float(hj_loss(base, cfg.inertia, nested_autograd)(t0, p0).detach()) or 1.0
    runners = [make_runner(n, base, cfg, METHODS[n]) for n in methods]
    for i in range(warmup):
        for r in runners:
            r.times.append(timed_step(r, *batches[i % n_batches], loss_scale, cfg.device))
    rec["compile"] = []
    if compile_methods:
        torch.compiler.reset()  # fresh caches: earlier configurations' graphs are done with
        # The fastest after warm-up (first iteration excluded: allocator growth, lazy init).
        warm = {r.name: statistics.median(r.times[1:] or r.times) for r in runners}
        ranked = sorted(warm, key=warm.__getitem__)
        todo = list(dict.fromkeys(ranked[0] if n == "fastest" else n for n in compile_methods))
        # Should the fastest not compile (nested autograd does not: AOTAutograd has no double
        # backward), the runner-up is tried instead, so that compilation is measured at all.
        spare = ranked[1] if "fastest" in compile_methods and len(ranked) > 1 else None
        while todo:
            name = todo.pop(0)
            cr, info = compile_runner(base, cfg, name, t0, p0, loss_scale, compile_timeout)
            rec["compile"].append(info)
            if cr is None:
                if name == ranked[0] and spare is not None and spare not in todo:
                    todo.append(spare)
                    spare = None
                continue
            for i in range(warmup):
                cr.times.append(timed_step(cr, *batches[i % n_batches], loss_scale, cfg.device))
            runners.append(cr)
    for r in runners:
        r.times.clear()

    for i in range(repeats):
        k = i % len(runners)
        for r in runners[k:] + runners[:k]:  # rotated, so no method always runs first
            r.times.append(timed_step(r, *batches[i % n_batches], loss_scale, cfg.device))

    base_median = statistics.median(runners[0].times)
    rec["methods"] = {
        r.name: {
            "median_s": statistics.median(r.times),
            "min_s": min(r.times),
            "iterations_per_s": 1.0 / statistics.median(r.times),
            "ratio_to_nested": statistics.median(r.times) / base_median,
            "times_s": r.times,
        }
        for r in runners
    }
    return rec


def print_table(results: dict[str, dict[str, Any]], device: str) -> None:
    # Threads matter: on a shared 2-core machine, 2 torch threads can run 20x slower than 1
    # (OpenMP workers spin while a neighbour holds their core).
    print(f"torch {torch.__version__}, {device}, {torch.get_num_threads()} threads")
    head = f"{'config':<12} {'method':<22} {'s/it (median)':>14} {'s/it (min)':>11} "
    print(head + f"{'it/s':>8} {'vs nested':>10}")
    for label, rec in results.items():
        for name, m in rec["methods"].items():
            print(
                f"{label:<12} {name:<22} {m['median_s']:>14.5f} {m['min_s']:>11.5f} "
                f"{m['iterations_per_s']:>8.1f} {m['ratio_to_nested']:>10.3f}"
            )
        for c in rec["compile"]:
            status = f"FAILED: {c.get('error')}"
            if c["ok"]:
                worst = max(c["check"].values())
                status = f"ok, warm-up {c['compile_seconds']:.1f} s, check error {worst:.1e}"
                if c["fullgraph"] != "ok":
                    status += f"; NOT one graph ({c['fullgraph']})"
            print(f"{'':<12} torch.compile({c['method']}): {status}")
        fastest = min(rec["methods"], key=lambda n: rec["methods"][n]["median_s"])
        print(f"{'':<12} fastest: {fastest}")
        worst = max(max(e.values()) for e in rec["checks"].values())
        print(f"{'':<12} checks vs nested autograd (float64): worst relative error {worst:.1e}")


def configurations(paper: bool) -> dict[str, TrainConfig]:
    """The benchmarked configurations (the paper preset only with ``--paper``: ~5-10 s/it)."""
    cfgs = {
        "default": TrainConfig(),
        "3x64-tp": TrainConfig(widths=(64, 64, 64), inputs="t,p", batch=4096),
    }
    if paper:
        cfgs["paper"] = TrainConfig(**PRESETS["paper"])
    return cfgs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=30, help="timed round-robin rounds")
    ap.add_argument("--warmup", type=int, default=5, help="untimed rounds before timing")
    ap.add_argument("--batches", type=int, default=4, help="pre-sampled batches, cycled")
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    ap.add_argument("--configs", nargs="+", help="subset of the configurations to run")
    ap.add_argument("--paper", action="store_true", help="also the paper preset (3 timed its)")
    ap.add_argument(
        "--compile",
        nargs="*",
        default=["fastest"],
        choices=[*METHODS, "fastest"],
        help="methods to torch.compile (default: the fastest in warm-up; none given: skip)",
    )
    ap.add_argument("--compile-timeout", type=float, default=120.0)
    ap.add_argument("--check-points", type=int, default=4096, help="points for the checks")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--json", default=None, help="write the results to this file")
    args = ap.parse_args()
    # Dynamo logs every graph break with a stack trace; the record keeps the first one anyway.
    torch._logging.set_logs(dynamo=logging.ERROR)
    if args.threads:
        torch.set_num_threads(args.threads)
    methods = ["nested", *(m for m in args.methods if m != "nested")]  # nested is the baseline
    cfgs = configurations(args.paper or "paper" in (args.configs or []))
    if args.configs:
        cfgs = {k: v for k, v in cfgs.items() if k in args.configs}
    results: dict[str, dict[str, Any]] = {}
    device = torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu"
    for label, cfg in cfgs.items():
        cfg = dataclasses.replace(cfg, device=args.device)
        paper = label == "paper"
        results[label] = bench_config(
            cfg,
            methods=methods,
            # The paper preset costs seconds per iteration on a CPU: 1 warm-up, ≤ 3 timed.
            repeats=min(args.repeats, 3) if paper else args.repeats,
            warmup=1 if paper else args.warmup,
            n_batches=1 if paper else args.batches,
            compile_methods=args.compile,
            compile_timeout=args.compile_timeout,
            check_points=args.check_points,
        )
        print(f"[{label}] done", flush=True)
    print_table(results, device)
    if args.json:
        meta = {
            "torch": torch.__version__,
            "device": device,
            "threads": torch.get_num_threads(),
            "repeats": args.repeats,
            "warmup": args.warmup,
        }
        with open(args.json, "w") as f:
            json.dump({"meta": meta, "results": results}, f, indent=1)


if __name__ == "__main__":
    main()
