"""Integrators behind one ``integrate()``: bisection integrators (learned or Taylor) and the
classical baselines, for any Lie–Poisson system, stepped in Rust."""

from __future__ import annotations

import math
import numbers
import os
import sys
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, overload

import numpy as np
from numpy.typing import ArrayLike

from . import _core
from .export import (
    DOMAIN_KINDS,
    load_generating,
    model_bytes,
    model_structure,
    parse_log_canonical_metadata,
    parse_metadata,
    read_tensor,
)
from .files import check_input_file
from .protocols import (
    NEWTON_MAX_ITER,
    NEWTON_TOL,
    ROLLOUT_KEYS,
    Stepper,
    as_stepper,
    as_system,
)
from .realizations.lie_groupoid import sou
from .structures.lie_poisson import HeavyTop, LiePoissonSystem, RigidBody
from .untrusted import parsing

if TYPE_CHECKING:
    import torch

    from .generating import GeneratingFunction

MODELS_PACKAGE = "poisson_rs.models"
DEFAULT_MODEL = "default"
#: Largest model file read (the paper's 253k-parameter model takes 2 MB).
MAX_MODEL_BYTES = 1 << 30


#: Smallest step accepted: the least normal float64 (2.2e-308). Below it 1/h and T/h overflow.
MIN_STEP = sys.float_info.min

#: Largest step count (n_steps, every) accepted: 2**53, the last integer float64 holds exactly,
#: so every recorded time k·h is the float it should be; a rollout that long would take
#: centuries, and past 2**64 the count does not even fit the core's integers.
MAX_COUNT = 2**53


def _check_step(h: Any, name: str = "h") -> float:
    """``h`` as a float: TypeError unless a real number (int, float, Fraction, Decimal, NumPy
    scalar; not a bool), ValueError unless finite and in [MIN_STEP, ∞) — ``10**400`` and 1e-320
    included, which would otherwise overflow later as OverflowError."""
    if isinstance(h, (bool, np.bool_)) or not isinstance(h, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(h).__name__}")
    try:
        value = float(h)
    except (OverflowError, ValueError, TypeError):
        raise ValueError(
            f"{name} must be finite and > 0, got a number too large for float64"
        ) from None
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be finite and > 0, got {value}")
    if value < MIN_STEP:
        raise ValueError(f"{name} = {value:g} is below {MIN_STEP:g}, the smallest step accepted")
    return value


def _check_time(t: Any, name: str = "t") -> float:
    """A time t >= 0 as a float: TypeError unless a real number (not a bool), ValueError unless
    finite (``10**400`` included, which float() would turn into OverflowError)."""
    if isinstance(t, (bool, np.bool_)) or not isinstance(t, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(t).__name__}")
    try:
        value = float(t)
    except (OverflowError, ValueError, TypeError):
        raise ValueError(f"{name} must be finite, got a number too large for float64") from None
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be finite and >= 0, got {value}")
    return value


def _check_count(name: str, value: Any, low: int = 0) -> int:
    """``value`` as an int in [low, MAX_COUNT]: TypeError unless an integer (Python or NumPy;
    not a bool, not a float), ValueError naming ``name`` outside the range (2**64 included,
    which would otherwise overflow as OverflowError on the way into the core)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__}")
    count = int(value)
    if count < low:
        raise ValueError(f"{name} must be >= {low}, got {count}")
    if count > MAX_COUNT:
        raise ValueError(f"{name} must be <= 2**53, got {count}")
    return count


#: Meaning of :attr:`RolloutInfo.failure_code` (0: no failure).
FAILURE_CODES: dict[int, str] = {
    1: "no convergence",
    2: "singular Jacobian",
    3: "non-finite value",
    4: "chart singular",
    5: "left the domain",
}


@dataclass(frozen=True)
class RolloutInfo:
    """Per-trajectory diagnostics of a rollout; every field has shape (n,)."""

    converged: np.ndarray
    """True when every step's Newton solve converged."""
    failed_step: np.ndarray
    """Index of the step that failed (state k → k+1), or −1."""
    failure_code: np.ndarray
    """0 none, 1 no convergence, 2 singular Jacobian, 3 non-finite value, 4 chart singular,
    5 left the domain (a log-canonical state left the positive orthant)."""
    newton_iterations: np.ndarray
    """Newton updates summed over the trajectory."""
    max_newton_iterations: np.ndarray
    """Most Newton updates in one step."""
    max_residual: np.ndarray
    """Largest accepted residual |tar(∂S/∂p, p) − μ|∞ over the steps."""
    out_of_domain: np.ndarray
    """int64: recorded states (the kept ones, every ``every``-th, the initial one included)
    outside the model's training domain; states between records are not checked, NaN states
    after a failure are not counted. Zeros for methods without a domain (Taylor, classical)."""
    step_angle: np.ndarray
    """float64, radians: h times the local rate at the initial state, max(‖ad_∇H(μ)‖_F/√2,
    ‖∂f/∂μ‖_F) with f the vector field (the Frobenius norm of the Jacobian carries the Hessian
    of H and bounds its spectral norm). Above :data:`MAX_STEP_ANGLE` no fixed-step method
    resolves the motion. NaN where it does not apply (adaptive DOP853, a stepper without a
    Lie–Poisson system)."""


class BisectionIntegrator:
    """A Poisson integrator read off the Lagrangian bisection of a generating function S(t, p).

    Steps run in the Rust core; :meth:`torch_step` is the same map in pure torch, for checking.
    Build one with :func:`load_model` (a learned S saved to a file) or :func:`taylor_integrator`
    (the truncated Taylor series of the exact S).
    """

    def __init__(
        self,
        source: Path | bytes,
        *,
        tol: float = NEWTON_TOL,
        max_iter: int = NEWTON_MAX_ITER,
        newton: Literal["simplified", "full"] = "simplified",
    ) -> None:
        if not (isinstance(tol, numbers.Real) and 0 < tol < 1):
            raise ValueError(f"tol must lie in (0, 1), got {tol!r}")
        if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
            raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")
        if newton not in ("simplified", "full"):
            raise ValueError(f"newton must be 'simplified' or 'full', got {newton!r}")
        self._source = source
        if isinstance(source, bytes):
            data = source
            where = "model bytes"
        else:
            # A FIFO would block the read and /dev/zero fill the memory: a bounded regular file.
            check_input_file(source, max_bytes=MAX_MODEL_BYTES, what="model file")
            data = Path(source).read_bytes()
            where = f"model file {source}"
        # The bytes the model was built from, read once: the core, the torch module
        # (`generating`) and a pickle are all built from them, never from the path again (a
        # later write may change the file, or turn it into a FIFO).
        self._bytes = data
        with parsing(where):  # MemoryError passes through as it is
            self._core = _core.Model.from_bytes(data)
        self.metadata: dict[str, Any] = parse_metadata(self._core.metadata, where)
        system: LiePoissonSystem = self.metadata["system"]
        with parsing(where, "system"):
            if system.dim != self._core.dim or not np.array_equal(
                system.algebra.c, self._core.structure_constants
            ):
                raise ValueError(
                    f"metadata 'system' ({system!r}) does not match the structure constants of "
                    f"the file's tensors (dimension {self._core.dim})"
                )
        with parsing(where, "widths"):
            if tuple(self._core.widths) != self.metadata["widths"]:
                raise ValueError(
                    f"metadata 'widths' says {list(self.metadata['widths'])} but the tensors "
                    f"hold {self._core.widths}"
                )
        with parsing(where, "domain"):
            self.domain: dict[str, Any] = _check_domain(self.metadata["domain"], self._core.dim)
        with parsing(where, "system"):
            _check_first_order(self._core, data, system, self.domain)
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self.newton = newton
        self._generating: GeneratingFunction | None = None
        self._stem: str | None = None

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickles as the model-file bytes and the Newton options (and the file's stem, which
        names a model whose metadata has no name); unpickling checks the bytes as loading does.
        """
        stem = self._source.stem if isinstance(self._source, Path) else None
        options = (self.tol, self.max_iter, self.newton)
        return (_restore_bisection, (type(self), self._bytes, options, stem))

    @property
    def path(self) -> Path | None:
        return self._source if isinstance(self._source, Path) else None

    @property
    def name(self) -> str:
        if isinstance(self._source, Path):
            default = self._source.stem
        else:
            default = getattr(self, "_stem", None) or "unnamed"
        return str(self.metadata.get("name", default))

    @property
    def chart(self) -> str:
        return str(self.metadata["chart"])

    @property
    def system(self) -> LiePoissonSystem:
        """The Lie–Poisson system the model integrates (from its file)."""
        return self.metadata["system"]  # type: ignore[no-any-return]

    @property
    def dim(self) -> int:
        """Dimension of the system's phase space g*."""
        return int(self._core.dim)

    @property
    def body(self) -> RigidBody:
        """The rigid body the model integrates; TypeError for another system."""
        system = self.system
        if not isinstance(system, RigidBody):
            raise TypeError(f"{self.name!r} integrates {system!r}, not a rigid body")
        return system

    @property
    def h_max(self) -> float:
        return float(self.metadata["h_max"])

    @property
    def n_parameters(self) -> int:
        """Trainable parameters of the MLP part (0 for a polynomial S)."""
        return int(self._core.n_parameters)

    @property
    def batch(self) -> int:
        """Trajectories a rollout solves together: a polynomial S (Taylor terms only) in
        lockstep Newton blocks with its jets in SIMD lanes, an MLP of 100 or more parameters with
        each layer one matrix product over the block; 1 (one at a time) for smaller MLPs. A
        trajectory's result does not depend on how the batch is chunked or threaded."""
        return int(self._core.batch)

    @property
    def generating(self) -> GeneratingFunction:
        """The torch generating function (built on first use: stepping in Rust needs no torch)."""
        if self._generating is None:
            from safetensors.numpy import load

            # From the bytes the core was built from, never the path again: a file replaced
            # since (or turned into a FIFO) would give torch another model than Rust, or hang.
            name = f"model file {self._source}" if self.path is not None else "model bytes"
            with parsing(name):
                tensors = load(self._bytes)
                self._generating = load_generating(tensors, self.metadata)
        return self._generating

    def torch_step(self, mu: torch.Tensor, h: float) -> torch.Tensor:
        """The step map in pure torch (autograd Newton), float64. mu: (B, n) → (B, n)."""
        import torch

        from .generating import bisection_step

        step = _check_step(h)
        mu = torch.as_tensor(mu, dtype=torch.float64)
        return bisection_step(
            self.generating, mu, step, chart=self.chart, tol=self.tol, max_iter=self.max_iter
        )

    def derivatives(self, t: float, p: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """S, ∂S/∂p, ∂²S/∂p² from the Rust core (forward mode).
        p: (B, n) → (B,), (B, n), (B, n, n)."""
        return self._core.derivatives(_check_time(t, "t"), _as_states(p, "p", self.dim)[0])

    def hj_residual(self, mu: ArrayLike, h: float) -> np.ndarray:
        """The model's Hamilton–Jacobi residual at (h, p = μ), relative to H(μ).

        r = ∂S/∂t(h, p) + H(sou(∂S/∂p(h, p), p)) vanishes for the exact S, and S = Σ t^k S_k
        truncated at order K leaves r = O(h^K); |r|/H(μ) says how far the step map of size h
        can be trusted near μ (e.g. along a trajectory). Derivatives come from the Rust core,
        sou from a NumPy copy of the chart map.

        mu: (..., n) states; h: time, finite and >= 0. Returns (...,) float64, signed, r/|H(μ)|
        (r itself where H(μ) = 0). Non-finite states, and states whose ∂S/∂p reaches the
        exponential chart's singularity, give NaN.
        """
        h = _check_time(h, "h")
        arr = np.asarray(mu)
        if arr.dtype == object or arr.dtype.kind not in "fiu":
            raise TypeError(f"mu must be an array of real numbers, got dtype {arr.dtype}")
        n = self.dim
        if arr.ndim == 0 or arr.shape[-1] != n:
            raise ValueError(f"mu must have shape (..., {n}), got {arr.shape}")
        p = np.ascontiguousarray(arr.reshape(-1, n), dtype=np.float64)
        out = np.full(len(p), np.nan)
        ok = np.isfinite(p).all(axis=1)
        q = np.ascontiguousarray(p[ok])
        _, grad, _ = self._core.derivatives(float(h), q)
        _, s_t = self._core.time_derivative(float(h), q)
        system = self.system
        algebra = None if system.algebra.is_so3() else system.algebra
        with np.errstate(invalid="ignore", over="ignore"):
            r = s_t + system.hamiltonian(sou(self.chart, grad, q, algebra=algebra))
        energy = np.abs(system.hamiltonian(q))
        out[ok] = r / np.where(energy > 0, energy, 1.0)
        return out.reshape(arr.shape[:-1])

    def rollout(
        self, mu0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        return _core.rollout_model(
            self._core,
            mu0,
            h,
            n_steps,
            every,
            self.tol,
            self.max_iter,
            self.newton == "simplified",
        )

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(name={self.name!r}, system={self.system!r}, "
            f"chart={self.chart!r}, parameters={self.n_parameters}, h_max={self.h_max})"
        )


def _restore_bisection(
    cls: type[BisectionIntegrator],
    data: bytes,
    options: tuple[float, int, Literal["simplified", "full"]],
    stem: str | None,
) -> BisectionIntegrator:
    """Unpickles a :class:`BisectionIntegrator` (see its ``__reduce__``)."""
    tol, max_iter, newton = options
    stepper = cls(data, tol=tol, max_iter=max_iter, newton=newton)
    stepper._stem = stem
    return stepper


class LearnedIntegrator(BisectionIntegrator):
    """A bisection integrator whose generating function was learned; see :func:`load_model`."""


class TaylorIntegrator(BisectionIntegrator):
    """The paper's classical approach: S truncated to its Taylor series in t; see
    :func:`taylor_integrator`."""


def list_models() -> list[str]:
    """Names of the models shipped with the package (loadable with ``load_model(name)``)."""
    root = resources.files(MODELS_PACKAGE)
    names = (p.name for p in root.iterdir() if p.name.endswith(".safetensors"))
    return sorted(n.removesuffix(".safetensors") for n in names)


def shipped_models(system: LiePoissonSystem) -> dict[str, LearnedIntegrator]:
    """The shipped models trained for ``system``, by name (a model of another system would be
    scored against the wrong flow)."""
    models = {name: load_model(name) for name in list_models()}
    return {name: m for name, m in models.items() if m.system == system}


def load_model(
    path: str | os.PathLike[str] | None = None,
    *,
    tol: float = NEWTON_TOL,
    max_iter: int = NEWTON_MAX_ITER,
    newton: Literal["simplified", "full"] = "simplified",
) -> LearnedIntegrator | LearnedLogCanonicalIntegrator | LearnedPolynomialIntegrator:
    """Loads a learned integrator.

    ``path`` is a model file, the name of a shipped model (see :func:`list_models`), or None for
    the default model. ``tol`` and ``max_iter`` set the Newton solve (relative update tolerance and
    iteration cap). Models large enough to be solved in batches (``batch > 1``, e.g. the paper's)
    use simplified Newton by default: the Jacobian of a step's first update is kept while the
    updates contract by 4× or more; ``newton="full"`` recomputes it every update. Both agree to
    ``tol``. Raises FileNotFoundError for a missing file, ValueError for a corrupt one or one
    whose metadata names an unknown ``structure``. A file recording ``structure =
    log_canonical`` loads as a :class:`LearnedLogCanonicalIntegrator`, one recording
    ``structure = polynomial`` as a :class:`LearnedPolynomialIntegrator` (full Newton always).
    """
    if path is None:
        path = DEFAULT_MODEL
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str, a path or None, got {type(path).__name__}")
    if isinstance(path, str) and path in list_models():
        path = str(resources.files(MODELS_PACKAGE).joinpath(f"{path}.safetensors"))
    elif not os.path.lexists(path):
        raise FileNotFoundError(
            f"no model file {os.fspath(path)!r}, and no shipped model of that name; shipped "
            f"models: {', '.join(list_models())}"
        )
    structure = model_structure(path)
    if structure == "log_canonical":
        return LearnedLogCanonicalIntegrator(Path(path), tol=tol, max_iter=max_iter)
    if structure == "polynomial":
        return LearnedPolynomialIntegrator(Path(path), tol=tol, max_iter=max_iter)
    return LearnedIntegrator(Path(path), tol=tol, max_iter=max_iter, newton=newton)


def taylor_integrator(
    system: Any = None,
    order: int = 3,
    chart: str | None = None,
    *,
    tol: float = NEWTON_TOL,
    max_iter: int = NEWTON_MAX_ITER,
) -> Stepper:
    """The Taylor-HJ integrator of ``order`` (S = Σ_{k≤order} t^k S_k, the S_k exact) for any
    Poisson system (default: the paper's rigid body), in ``chart``, one of
    ``system.taylor_charts()`` (default: the first; "cayley" on the rigid body, "exp" on any
    other Lie–Poisson system, "log" on a log-canonical one, "realization" on a polynomial
    bivector).

    Its order of accuracy is ``order``, or ``order + 1`` where S_{order+1} vanishes (odd orders
    for a quadratic Hamiltonian). ``tol`` and ``max_iter`` set the Newton solve of every step
    (relative update, iteration cap), the same defaults on every structure.

    >>> import poisson_rs as pr
    >>> lv = pr.lotka_volterra([[0, 1], [-1, 0]], [1, 2])
    >>> pr.integrate(pr.taylor_integrator(lv, 3), [1.0, 0.8], h=0.1, n_steps=10).shape
    (11, 2)
    """
    system = RigidBody() if system is None else as_system(system)
    _check_newton(tol, max_iter)
    return system.taylor_integrator(order, chart, tol=tol, max_iter=max_iter)


def _check_newton(tol: Any, max_iter: Any) -> None:
    """ValueError naming ``tol`` or ``max_iter`` outside (0, 1) / the integers >= 1."""
    if isinstance(tol, bool) or not (isinstance(tol, numbers.Real) and 0 < tol < 1):
        raise ValueError(f"tol must lie in (0, 1), got {tol!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
        raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")


def lie_poisson_taylor(
    body: LiePoissonSystem,
    order: int,
    chart: str,
    *,
    tol: float = NEWTON_TOL,
    max_iter: int = NEWTON_MAX_ITER,
) -> TaylorIntegrator:
    """Taylor-HJ on the groupoid T*G of a Lie–Poisson system in ``chart`` ("cayley": the rigid
    body only; "exp": any algebra), through the learned models' Newton stepper."""
    from .taylor import system_taylor_terms

    if isinstance(order, bool) or not isinstance(order, numbers.Integral) or order < 1:
        raise ValueError(f"order must be an integer >= 1, got {order!r}")
    powers, coeffs = system_taylor_terms(body, int(order), chart)
    data = model_bytes(
        powers=powers,
        coeffs=coeffs,
        layers=[],
        mlp_power=1,
        chart=chart,
        system=body,
        h_max=float("inf"),
        domain={"kind": "all"},
        taylor_order=int(order),
        record={"name": f"taylor{order}-{chart}"},
    )
    return TaylorIntegrator(data, tol=tol, max_iter=max_iter)


def _check_domain(domain: Mapping[str, Any], dim: int | None = None) -> dict[str, Any]:
    """A training domain from a model's metadata, with the numbers its kind needs checked.

    Raises ValueError for a shell without finite 0 <= r_min < r_max, a cube without a finite
    half_width > 0, a top on a model whose dimension ``dim`` is not 6, or another kind than
    "shell", "cube", "top" and "all".
    """

    def number(key: str) -> float:
        v = domain.get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"metadata 'domain' needs a finite number {key!r}: {dict(domain)!r}")
        return float(v)

    kind = domain.get("kind")
    if kind not in DOMAIN_KINDS:
        raise ValueError(
            f"metadata 'domain' must be a cube, a shell, a top or all: {dict(domain)!r}"
        )
    if kind in ("shell", "top"):
        r_min, r_max = number("r_min"), number("r_max")
        if not 0 <= r_min < r_max:
            raise ValueError(f"metadata 'domain' needs 0 <= r_min < r_max: {dict(domain)!r}")
    if kind in ("cube", "top") and not number("half_width") > 0:
        raise ValueError(f"metadata 'domain' needs half_width > 0: {dict(domain)!r}")
    if kind == "top" and dim is not None and dim != 6:
        # (M, Γ) ∈ se(3)*: the top's bounds index six components.
        raise ValueError(
            f"metadata 'domain' is a top (for se(3)*, dimension 6) but the model has dimension "
            f"{dim}: {dict(domain)!r}"
        )
    return dict(domain)


#: Largest relative RMS difference between ∂S/∂t(0, p) and −H(p) accepted at load: round-off
#: where the t¹ terms are exact polynomials (float32 training stores them rounded to float32:
#: 2e-8 measured), and the training error where an MLP multiplied by t¹ (``mlp_power = 1``, the
#: paper's ansatz) learns them (1.6 % for the shipped paper model).
FIRST_ORDER_TOL_EXACT = 1e-6
FIRST_ORDER_TOL_LEARNED = 0.05
#: Seeded sample of the training domain on which the t¹ terms are compared.
_FIRST_ORDER_SAMPLES = 512


def _domain_sample(domain: Mapping[str, Any], dim: int, n: int) -> np.ndarray:
    """``n`` states in a training domain (deterministic: seed 0); radii 0.5 to 3 for "all"."""
    rng = np.random.default_rng(0)
    kind = domain["kind"]

    def shell(d: int, r_min: float, r_max: float) -> np.ndarray:
        u = rng.normal(size=(n, d))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        return u * rng.uniform(r_min, r_max, size=(n, 1))

    if kind == "cube":
        return rng.uniform(-domain["half_width"], domain["half_width"], size=(n, dim))
    if kind == "shell":
        return shell(dim, domain["r_min"], domain["r_max"])
    if kind == "top":
        m = rng.uniform(-domain["half_width"], domain["half_width"], size=(n, 3))
        return np.concatenate([m, shell(dim - 3, domain["r_min"], domain["r_max"])], axis=1)
    return shell(dim, 0.5, 3.0)


def _check_first_order(
    core: Any, data: bytes, system: LiePoissonSystem, domain: Mapping[str, Any]
) -> None:
    """ValueError unless the t¹ terms of the model's S are −t·H of the system its metadata
    records: S = −tH + O(t²) for every generating function of the flow of H (the
    Hamilton–Jacobi equation at t = 0, where ∂S/∂p = 0 and sou = p). A file whose metadata was
    edited to claim another system (another inertia, say) would otherwise load cleanly, run the
    original body and report the claimed one.

    Where the polynomial part holds t¹ terms (the exact Taylor terms a writer put there) they
    must match to round-off, whatever an MLP adds. Where it holds none and the MLP carries t¹
    (``mlp_power = 1``, the paper's ansatz) the learned ∂S/∂t(0, p) must be within the training
    error, FIRST_ORDER_TOL_LEARNED. Compared on a seeded sample of the training domain.

    A system recorded with no Hamiltonian (H unknown: a map learned from trajectories alone,
    ``pr.learn(mode="map")``) claims no H, so there is nothing to compare against."""
    if not system.polynomial.terms:
        return
    p = _domain_sample(domain, core.dim, _FIRST_ORDER_SAMPLES)
    powers = read_tensor(data, "poly.powers")
    coeffs = read_tensor(data, "poly.coeffs")
    first = None if powers is None or coeffs is None else powers[:, 0] == 1
    with np.errstate(all="ignore"):
        energy = np.asarray(system.hamiltonian(p), dtype=np.float64)
        if first is not None and first.any():
            exps, cs = powers[first, 1:], coeffs[first]
            s_1 = np.prod(p[:, None, :] ** exps[None, :, :], axis=-1) @ cs
            tol, what = FIRST_ORDER_TOL_EXACT, "polynomial t¹ terms"
        elif core.mlp_power == 1:
            s_1 = core.time_derivative(0.0, p)[1]
            tol, what = FIRST_ORDER_TOL_LEARNED, "learned t¹ terms"
        else:
            s_1 = np.zeros(len(p))
            tol, what = FIRST_ORDER_TOL_EXACT, "t¹ terms (it has none)"
        scale = math.sqrt(float(np.mean(energy**2)))
        diff = math.sqrt(float(np.mean((s_1 + energy) ** 2)))
    rel = diff / scale if scale > 0 else diff
    if not rel <= tol:  # NaN fails too
        raise ValueError(
            f"the model's {what} are not -t·H of the system its metadata records "
            f"({system!r}): relative RMS difference {rel:.3g} over its training domain, "
            f"tolerance {tol:g}. The metadata was edited or belongs to another model: the "
            "tensors integrate another system"
        )


#: Trajectory-states per block of :func:`count_out_of_domain`: its temporaries stay a few MB
#: whatever the size of the rollout.
_DOMAIN_BLOCK = 1 << 16


def count_out_of_domain(domain: Mapping[str, Any] | None, traj: np.ndarray) -> np.ndarray:
    """States of ``traj`` (n, records, dim) outside a training ``domain``, per trajectory: (n,)
    int64.

    Shell: |μ| outside [r_min, r_max]; cube: some |μᵢ| > half_width; top (μ = (M, Γ)): some
    |Mᵢ| > half_width or |Γ| outside [r_min, r_max]; "all" or None: none.
    NaN states (after a Newton failure) compare false and are not counted. Works through the
    trajectory in blocks, so its memory does not grow with the output.
    """
    kind = None if domain is None else domain.get("kind")
    counts = np.zeros(traj.shape[0], dtype=np.int64)
    if domain is None or kind not in ("shell", "cube", "top") or traj.size == 0:
        return counts
    rows = max(1, _DOMAIN_BLOCK // max(1, traj.shape[1]))
    for start in range(0, traj.shape[0], rows):
        block = traj[start : start + rows]
        if kind == "shell":
            r2 = np.einsum("nrd,nrd->nr", block, block)
            outside = (r2 < domain["r_min"] ** 2) | (r2 > domain["r_max"] ** 2)
        elif kind == "top":
            g2 = np.einsum("nrd,nrd->nr", block[..., 3:], block[..., 3:])
            outside = (np.abs(block[..., :3]) > domain["half_width"]).any(axis=-1)
            outside |= (g2 < domain["r_min"] ** 2) | (g2 > domain["r_max"] ** 2)
        else:
            outside = (np.abs(block) > domain["half_width"]).any(axis=-1)
        counts[start : start + rows] = outside.sum(axis=1, dtype=np.int64)
    return counts


def _describe_domain(domain: Mapping[str, Any]) -> str:
    if domain["kind"] == "shell":
        return f"the shell {domain['r_min']:g} <= |mu| <= {domain['r_max']:g}"
    if domain["kind"] == "top":
        return (
            f"|M_i| <= {domain['half_width']:g} and "
            f"{domain['r_min']:g} <= |Gamma| <= {domain['r_max']:g}"
        )
    return f"the cube |mu_i| <= {domain['half_width']:g}"


#: NumPy's native float64 dtype (one object: compared by identity on the fast path).
_FLOAT64 = np.dtype(np.float64)


def _as_states(
    mu0: Any, what: str = "mu0", dim: int = 3, *, check_finite: bool = True
) -> tuple[np.ndarray, bool]:
    """(n, dim) C-contiguous float64 array of an array-like of states (mu0 itself where it is
    one already), and whether it was one state. ``check_finite=False`` leaves the NaN/∞ check
    to a caller whose core makes it (with the same message)."""
    if type(mu0) is np.ndarray:
        arr = mu0
    else:
        if isinstance(mu0, np.ma.MaskedArray):
            # np.asarray would drop the mask and step the masked values as if they were data.
            raise TypeError(
                f"{what} is a numpy masked array, whose mask would be ignored; pass plain data "
                "(e.g. the unmasked rows, or .filled(value))"
            )
        arr = np.asarray(mu0)
    dtype = arr.dtype
    if dtype is not _FLOAT64:
        if dtype.kind not in "fiu":  # object, bool, complex, strings, ...
            raise TypeError(f"{what} must be an array of real numbers, got dtype {dtype}")
        arr = arr.astype(np.float64)
    shape = arr.shape
    if shape == (dim,):
        single = True
        arr = arr.reshape(1, dim)
    elif len(shape) == 2 and shape[1] == dim:
        single = False
    else:
        raise ValueError(f"{what} must have shape ({dim},) or (n, {dim}), got {shape}")
    if not arr.flags.c_contiguous:
        arr = np.ascontiguousarray(arr)
    if check_finite and not np.isfinite(arr).all():
        raise ValueError(f"{what} holds NaN or infinite values")
    return arr, single


@overload
def integrate(
    stepper: Stepper,
    mu0: Any,
    h: float,
    n_steps: int,
    *,
    every: int = ...,
    return_info: Literal[False] = ...,
    on_failure: Literal["warn", "raise", "ignore"] = ...,
    strict: bool = ...,
) -> np.ndarray: ...


@overload
def integrate(
    stepper: Stepper,
    mu0: Any,
    h: float,
    n_steps: int,
    *,
    every: int = ...,
    return_info: Literal[True],
    on_failure: Literal["warn", "raise", "ignore"] = ...,
    strict: bool = ...,
) -> tuple[np.ndarray, RolloutInfo]: ...


def integrate(
    stepper: Stepper,
    mu0: Any,
    h: float,
    n_steps: int,
    *,
    every: int = 1,
    return_info: bool = False,
    on_failure: Literal["warn", "raise", "ignore"] = "warn",
    strict: bool = True,
) -> np.ndarray | tuple[np.ndarray, RolloutInfo]:
    """Advances initial states ``n_steps`` steps of size ``h``, keeping every ``every``-th state.

    Parameters
    ----------
    stepper: an integrator, e.g. from :func:`load_model`.
    mu0: (dim,) or (n, dim) array-like of states in g* (angular momenta for the rigid body, dim
        = 3; (M, Γ) for the heavy top, dim = 6).
    h: step size (time units), finite and > 0.
    n_steps: number of steps, >= 0.
    every: keep states 0, every, 2·every, ... (bounds memory on long horizons).
    return_info: also return a :class:`RolloutInfo`.
    on_failure: a trajectory whose Newton solve fails stops there and its later states are NaN;
        "warn" (default) warns once per call, "raise" raises RuntimeError, "ignore" stays silent.
    strict: a learned model refuses steps beyond the h_max it was trained for (ValueError);
        ``strict=False`` lets it extrapolate.

    Returns
    -------
    float64 array (n_steps // every + 1, dim) for one state, (n, n_steps // every + 1, dim) for
    n. A ``dask.array.Array`` mu0 gives a lazy dask array chunked as mu0 along axis 0 (and the
    info as dask arrays), bit-identical once computed: see
    :func:`poisson_rs.ensembles.integrate_dask`.

    A model that records its training domain (a shell or a cube of states) is checked against
    it: ``info.out_of_domain`` counts, per trajectory, the recorded states (only the kept ones,
    every ``every``-th) outside it, and one RuntimeWarning per call says so when any are. Its
    ``hj_residual`` tells how well it solves its equation there. Ctrl-C interrupts a long
    rollout (KeyboardInterrupt) within a fraction of a second.

    When ``every`` does not divide ``n_steps`` the last recorded state is step
    ``n_steps - n_steps % every``, NOT the final one (n_steps = 10, every = 3 keeps steps 0, 3,
    6, 9): choose ``every`` dividing ``n_steps`` to keep the final state.
    """
    # A stepper whose core checks the states and keeps its diagnostics until asked for (see
    # ClassicalIntegrator._core_rollout).
    core_rollout = getattr(stepper, "_core_rollout", None)
    if (
        core_rollout is not None
        and (type(mu0) is list or type(mu0) is np.ndarray)
        and type(h) is float
        and MIN_STEP <= h < math.inf
        and type(n_steps) is int
        and 0 <= n_steps <= MAX_COUNT
        and type(every) is int
        and 1 <= every <= MAX_COUNT
        and not n_steps % every
        and not return_info
    ):
        # The thin path of a small call: every argument of a built-in type in range, no info
        # asked for; nothing else to check but on_failure, and nothing to report unless the
        # core's summary says so.
        if on_failure not in _ON_FAILURE:
            raise ValueError(f"on_failure must be 'warn', 'raise' or 'ignore', got {on_failure!r}")
        # A list of plain numbers, one state, goes to the core as it is (NumPy's conversion
        # of a short list costs more than the step); the core returns None for another list.
        result = core_rollout(mu0, h, n_steps, every) if type(mu0) is list else None
        if result is None:
            arr, single = _as_states(mu0, dim=stepper.dim, check_finite=False)
            result = core_rollout(arr, h, n_steps, every)
        else:
            single = True
        traj, diagnostics = result
        summary = diagnostics.summary()
        if summary[0] or summary[4] > MAX_STEP_ANGLE:  # NaN compares false
            _report(stepper, h, len(traj), summary, on_failure)
        return traj[0] if single else traj
    if core_rollout is None:
        as_stepper(stepper)
    # A dask array exists only once dask.array is imported (and is no list or ndarray).
    if type(mu0) is not list and type(mu0) is not np.ndarray and "dask.array" in sys.modules:
        from .ensembles import integrate_dask, is_dask_array

        if is_dask_array(mu0):
            return integrate_dask(  # type: ignore[return-value]
                stepper,
                mu0,
                h,
                n_steps,
                every=every,
                return_info=return_info,
                on_failure=on_failure,
                strict=strict,
            )
    arr, single = _as_states(
        mu0, dim=int(getattr(stepper, "dim", 3)), check_finite=core_rollout is None
    )
    # Exact built-in types in range take the short path: the abstract-number checks cost more
    # than a small rollout. Anything else (Fraction, NumPy scalars, 10**400, 2**64, tiny h) gets
    # the full checks, which name the argument.
    if not (type(h) is float and MIN_STEP <= h < math.inf):
        h = _check_step(h)
    if not (type(n_steps) is int and 0 <= n_steps <= MAX_COUNT):
        n_steps = _check_count("n_steps", n_steps)
    if not (type(every) is int and 1 <= every <= MAX_COUNT):
        every = _check_count("every", every, 1)
    if n_steps % every:
        warnings.warn(
            f"every = {every} does not divide n_steps = {n_steps}: the last "
            f"{n_steps % every} steps are taken but their final state is not recorded",
            RuntimeWarning,
            stacklevel=2,
        )
    if on_failure not in _ON_FAILURE:
        raise ValueError(f"on_failure must be 'warn', 'raise' or 'ignore', got {on_failure!r}")
    # A learned stepper knows the largest step it was trained for and, for some, the states.
    h_max = getattr(stepper, "h_max", math.inf)
    if strict and isinstance(h_max, float) and math.isfinite(h_max) and h > h_max:
        raise ValueError(
            f"h = {h} exceeds h_max = {h_max}, the largest step "
            f"{getattr(stepper, 'name', type(stepper).__name__)!r} was trained for; pass "
            "strict=False to extrapolate (poisson-rs demo: --no-strict)"
        )
    domain = getattr(stepper, "domain", None)
    if not isinstance(domain, Mapping):
        domain = None
    h = float(h)
    raw: dict[str, np.ndarray] | None
    if core_rollout is not None:
        traj, diagnostics = core_rollout(arr, h, int(n_steps), int(every))
        summary = diagnostics.summary()
        raw = diagnostics.arrays() if return_info else None
    else:
        traj, raw = _checked_rollout(stepper, arr, h, int(n_steps), int(every))
        if "step_angle" not in raw:
            raw["step_angle"] = _step_angles(stepper, arr, h)
        summary = _summary(raw)
    out_of_domain = None
    if domain is not None:
        # Vectorised over the recorded states: cheap next to the rollout that made them.
        out_of_domain = count_out_of_domain(domain, traj)
    _report(stepper, h, len(arr), summary, on_failure, domain, out_of_domain)
    out = traj[0] if single else traj
    if not return_info:
        return out
    assert raw is not None
    if out_of_domain is None:
        out_of_domain = np.zeros(len(arr), dtype=np.int64)
    return out, RolloutInfo(**raw, out_of_domain=out_of_domain)


_ON_FAILURE = ("warn", "raise", "ignore")


def dop853_rollout(
    system: Any, x0: np.ndarray, h: float, n_steps: int, every: int, tol: float
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The rollout of every structure's "dop853": ``system.reference_solution`` at rtol = atol
    = ``tol`` sampled at t = k·every·h. A trajectory DOP853 cannot finish (over its budget,
    overflowing) is NaN from there on and reported like a failed step (code 1), the others
    are kept; no Newton solve, no step angle (it chooses its own steps)."""
    times = h * np.arange(0, n_steps // every + 1, dtype=np.float64) * every
    with warnings.catch_warnings():
        # integrate() reports the failed trajectories itself, once.
        warnings.filterwarnings("ignore", "DOP853 gave up", RuntimeWarning)
        traj = system.reference_solution(x0, times, rtol=tol, atol=tol, failures="nan")
    n = x0.shape[0]
    finite = np.isfinite(traj).all(axis=-1)
    converged = finite.all(axis=1)
    first_bad = np.where(converged, -1, np.argmin(finite, axis=1) * every - 1)
    return traj, {
        "converged": converged,
        "failed_step": first_bad.astype(np.int64),
        "failure_code": np.where(converged, 0, 1).astype(np.int8),
        "newton_iterations": np.zeros(n, dtype=np.uint64),
        "max_newton_iterations": np.zeros(n, dtype=np.uint32),
        "max_residual": np.full(n, np.nan),
        "step_angle": np.full(n, np.nan),
    }


def _checked_rollout(
    stepper: Stepper, x0: np.ndarray, h: float, n_steps: int, every: int
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """``stepper.rollout`` with its result checked against the :class:`Stepper` contract and
    its diagnostics completed: a key a stepper leaves out is inferred from the trajectory
    where it can be (a trajectory with a non-finite record failed, code 3, at the step of its
    first one) and unknown (NaN, or 0 Newton updates) elsewhere."""
    n, records = len(x0), n_steps // every + 1
    out = stepper.rollout(x0, h, n_steps, every)
    traj, info = out if isinstance(out, tuple) and len(out) == 2 else (out, {})
    traj = np.asarray(traj)
    if traj.shape != (n, records, x0.shape[1]) or not isinstance(info, Mapping):
        raise TypeError(
            f"{_stepper_name(stepper)}.rollout must return (traj, info) with traj of shape "
            f"{(n, records, x0.shape[1])} and info a dict; got "
            f"{getattr(traj, 'shape', type(traj).__name__)} and {type(info).__name__}"
        )
    raw = {k: np.asarray(v) for k, v in info.items()}
    for key, value in raw.items():
        if key in ROLLOUT_KEYS and value.shape != (n,):
            raise TypeError(
                f"{_stepper_name(stepper)}.rollout: info[{key!r}] must have shape ({n},), "
                f"got {value.shape}"
            )
    if "converged" not in raw:
        bad = ~np.isfinite(traj).all(axis=2)  # (n, records)
        first = np.where(bad.any(axis=1), bad.argmax(axis=1), -1)
        raw["converged"] = first < 0
        raw.setdefault("failed_step", np.where(first < 0, -1, np.maximum(first - 1, 0) * every))
        raw.setdefault("failure_code", np.where(first < 0, 0, 3))
    raw.setdefault("failed_step", np.full(n, -1, dtype=np.int64))
    raw.setdefault("failure_code", np.zeros(n, dtype=np.int64))
    raw.setdefault("newton_iterations", np.zeros(n, dtype=np.int64))
    raw.setdefault("max_newton_iterations", np.zeros(n, dtype=np.int64))
    raw.setdefault("max_residual", np.full(n, np.nan))
    return np.ascontiguousarray(traj, dtype=np.float64), raw


def _report(
    stepper: Any,
    h: float,
    n: int,
    summary: tuple[int, int, int, int, float, int],
    on_failure: str,
    domain: Mapping[str, Any] | None = None,
    out_of_domain: np.ndarray | None = None,
) -> None:
    """The warnings of :func:`integrate` (called from it: stacklevel 3 names its caller), in
    this order: a step that does not resolve the motion, recorded states outside a model's
    training domain, failed trajectories (RuntimeError with ``on_failure="raise"``).
    ``summary`` is (n_failed, first failed, its step, its code, max step angle, its index), as
    :func:`_summary` and ``_core.RolloutDiagnostics.summary()`` give it."""
    n_failed, first, failed_step, code, top, worst = summary
    if top > MAX_STEP_ANGLE:  # NaN (no angle known) compares false
        _warn_angle(stepper, top, worst, h, stacklevel=4)
    if domain is not None and out_of_domain is not None:
        n_outside = int(out_of_domain.sum())
        if n_outside:
            n_traj = int((out_of_domain > 0).sum())
            warnings.warn(
                f"{_stepper_name(stepper)}: {n_outside} recorded states of {n_traj} of "
                f"{len(out_of_domain)} trajectories lie outside the training domain "
                f"({_describe_domain(domain)}); the model extrapolates there (see "
                "info.out_of_domain and hj_residual)",
                RuntimeWarning,
                stacklevel=3,
            )
    if n_failed and on_failure != "ignore":
        msg = (
            f"{_stepper_name(stepper)}: {n_failed} of {n} trajectories failed "
            f"(first: trajectory {first} at step {failed_step}: "
            f"{FAILURE_CODES.get(code, f'code {code}')}); their later states are NaN"
        )
        if on_failure == "raise":
            raise RuntimeError(msg)
        warnings.warn(msg, RuntimeWarning, stacklevel=3)


def _summary(raw: Mapping[str, np.ndarray]) -> tuple[int, int, int, int, float, int]:
    """What :func:`integrate` warns about, from the diagnostic arrays of a rollout: as
    ``_core.RolloutDiagnostics.summary()``, (n_failed, first failed trajectory, its failed
    step, its failure code, the largest step angle ignoring NaN, its index); −1 and NaN for
    none."""
    converged = raw["converged"]
    n_failed = 0 if converged.all() else int((~converged).sum())
    first = step = code = -1
    if n_failed:
        first = int(np.flatnonzero(~converged)[0])
        step, code = int(raw["failed_step"][first]), int(raw["failure_code"][first])
    angle = raw["step_angle"]
    if not len(angle) or np.isnan(angle).all():
        return n_failed, first, step, code, math.nan, -1
    worst = int(np.nanargmax(angle))
    return n_failed, first, step, code, float(angle[worst]), worst


#: Largest angle h·ρ a step may turn the state by (ρ the local rate, see
#: :attr:`RolloutInfo.step_angle`; |ω| for the rigid body) before :func:`integrate` warns: beyond
#: a quarter turn no fixed-step method resolves the motion (fewer than 4 steps a revolution), and
#: a Taylor series is beyond its range.
MAX_STEP_ANGLE = 0.5 * math.pi


def _step_angles(stepper: Any, states: np.ndarray, h: float) -> np.ndarray:
    """h × the local rate at each of ``states`` (n, dim) (see :attr:`RolloutInfo.step_angle`),
    from the stepper's system (``system.step_angles``); NaN for an adaptive stepper, which
    chooses its own steps, and for a system that does not know its rate."""
    angles = getattr(getattr(stepper, "system", None), "step_angles", None)
    if angles is None or getattr(stepper, "adaptive", False):
        return np.full(len(states), np.nan)
    return np.asarray(angles(states, h), dtype=np.float64)


def _warn_unresolved(stepper: Any, angle: np.ndarray, h: float) -> None:
    """Warns when a step of size h turns some initial state by more than MAX_STEP_ANGLE: the
    result would be O(1) wrong while every step "converged" (a fixed-step method cannot see it).
    ``angle`` is :attr:`RolloutInfo.step_angle`, one per trajectory (every state is checked);
    NaN angles (DOP853) are skipped."""
    if not len(angle) or np.isnan(angle).all():
        return
    worst = int(np.nanargmax(angle))
    if angle[worst] > MAX_STEP_ANGLE:
        _warn_angle(stepper, float(angle[worst]), worst, h, stacklevel=4)


def _warn_angle(stepper: Any, top: float, worst: int, h: float, stacklevel: int = 3) -> None:
    """The warning of :func:`_warn_unresolved`: state ``worst`` turns by ``top`` rad a step."""
    rate = top / h
    warnings.warn(
        f"{_stepper_name(stepper)}: a step of h = {h:g} turns state {worst} by "
        f"{top:.3g} rad (h × the local rate max(‖ad_∇H‖_F/√2, ‖∂f/∂μ‖_F)), more than a "
        f"quarter turn: no fixed-step method resolves this motion and the result can be O(1) "
        f"wrong with every step converged; use h <= {MAX_STEP_ANGLE / rate:.3g} (see "
        "info.step_angle)",
        RuntimeWarning,
        stacklevel=stacklevel,
    )


def _stepper_name(stepper: Any) -> str:
    """How warnings name an integrator: its name ("learned" model, Taylor, classical method)."""
    name = getattr(stepper, "name", None)
    return f"{type(stepper).__name__} {name!r}" if name else type(stepper).__name__


#: Order of accuracy and whether the step is a Poisson map, for each classical integrator of the
#: rigid body.
CLASSICAL_METHODS: dict[str, tuple[int, bool]] = {
    "rk4": (4, False),
    "midpoint": (2, True),
    "splitting": (2, True),
    "splitting4": (4, True),
    "dmv": (2, True),
    "splitting_casimir": (2, True),
    "dop853": (8, False),
}

#: The same for any other Lie–Poisson system ("splitting": the heavy top only). The implicit
#: midpoint rule keeps quadratic Casimirs and is a Poisson map for quadratic Hamiltonians only.
LIE_POISSON_METHODS: dict[str, tuple[int, bool]] = {
    "rk4": (4, False),
    "midpoint": (2, False),
    "splitting": (2, True),
    "dop853": (8, False),
}


def classical_methods(system: Any) -> list[str]:
    """Names of the classical integrators :func:`classical` builds for ``system``, exactly."""
    return list(as_system(system).classical_methods())


class ClassicalIntegrator:
    """A classical baseline for a Lie–Poisson system, driven by :func:`integrate`.

    Build one with :func:`classical`. Every method but "dop853" takes fixed steps of size ``h`` in
    the Rust core, through the same parallel rollout as the bisection integrators, so timings
    compare like for like. For the rigid body μ̇ = μ × (μ/I):

    - "rk4": classical explicit Runge–Kutta, order 4; not Poisson (C and H drift).
    - "midpoint": implicit midpoint, order 2, Newton with the exact Jacobian; keeps C and H up
      to the Newton tolerance (both are quadratic).
    - "splitting": McLachlan's Lie–Poisson splitting H = Σ μᵢ²/(2Iᵢ), Strang-composed
      H₁(h/2) H₂(h/2) H₃(h) H₂(h/2) H₁(h/2); explicit, order 2, keeps C to round-off.
    - "splitting4": Suzuki's 5-stage composition of that Strang step, weights
      (p, p, 1 − 4p, p, p) with p = 1/(4 − 4^{1/3}); order 4, keeps C to round-off.
    - "dmv": the discrete Moser–Veselov algorithm, order 2, Newton for its rotation; keeps C and
      H to round-off.
    - "splitting_casimir": the Casimir split off first (Fassò; McLachlan): H = C/(2I_r) +
      Σ_{i≠r} ½(1/Iᵢ − 1/I_r)μᵢ² with I_r the median moment, the Casimir's flow the identity, the
      other two axis flows Strang-composed; order 2, 3 rotations a step, keeps C to round-off.
      For a nearly symmetric body its error nearly vanishes, where "splitting"'s does not.
    - "dop853": SciPy's adaptive DOP853 (:func:`~poisson_rs.reference.dop853_solution`, one
      trajectory at a time, in Python) with rtol = atol = ``tol``. It chooses its own steps:
      ``h`` sets only where the output is sampled (t = k·h), not the accuracy or the cost.

    For any other system: "rk4", "midpoint" (exact Jacobian by forward-mode dual numbers; keeps
    quadratic Casimirs), "dop853" (:func:`~poisson_rs.reference.reference_solution` with rtol =
    atol = ``tol``), and for the heavy top "splitting": Strang's V(h/2) K(h) V(h/2) of the
    potential flow (Γ fixed, Ṁ = mgl Γ × χ, exact) and the kinetic flow (the rigid body's
    splitting, turning M and Γ together); order 2, keeps |Γ|² and M·Γ to round-off.

    ``tol`` and ``max_iter`` set the Newton solve of the implicit methods (relative update
    tolerance and iteration cap, as for the bisection integrators); for "dop853" ``tol`` is its
    rtol and atol.
    """

    def __init__(
        self,
        body: LiePoissonSystem,
        name: str,
        *,
        tol: float = NEWTON_TOL,
        max_iter: int = NEWTON_MAX_ITER,
    ) -> None:
        if not isinstance(body, LiePoissonSystem):
            raise TypeError(f"body must be a LiePoissonSystem, got {type(body).__name__}")
        names = body.classical_methods()
        if not (isinstance(name, str) and name in names):
            raise ValueError(
                f"unknown classical integrator {name!r} for {body!r}; valid names: "
                f"{', '.join(names)}"
            )
        if isinstance(tol, bool) or not (isinstance(tol, numbers.Real) and 0 < tol < 1):
            raise ValueError(f"tol must lie in (0, 1), got {tol!r}")
        if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
            raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")
        self.body = body
        self.name = name
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self._dim = int(body.dim)  # systems are immutable; read on every integrate() call

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickles as the system, the method's name and the options; unpickling checks them."""
        return (_restore_classical, (type(self), self.body, self.name, self.tol, self.max_iter))

    @property
    def system(self) -> LiePoissonSystem:
        return self.body

    @property
    def dim(self) -> int:
        return self._dim

    def _table(self) -> dict[str, tuple[int, bool]]:
        return CLASSICAL_METHODS if isinstance(self.body, RigidBody) else LIE_POISSON_METHODS

    @property
    def order(self) -> int:
        """Order of accuracy (8 for DOP853, whose error is set by ``tol`` rather than h)."""
        return self._table()[self.name][0]

    @property
    def poisson(self) -> bool:
        """Whether a step is a Poisson map (keeps every Casimir to round-off)."""
        return self._table()[self.name][1]

    @property
    def adaptive(self) -> bool:
        """Whether it chooses its own steps (DOP853): ``h`` then only spaces the output."""
        return self.name == "dop853"

    @property
    def _core_rollout(self) -> Any:
        """The rollout in the Rust core that checks the states itself (NaN/∞ included) and
        returns ``(traj, _core.RolloutDiagnostics)``, for :func:`integrate`'s thin path; None
        for DOP853 (SciPy)."""
        return None if self.name == "dop853" else self._rust_rollout

    def _rust_rollout(
        self, mu0: np.ndarray | list[Any], h: float, n_steps: int, every: int, lazy: bool = True
    ) -> tuple[np.ndarray, Any] | None:
        """``(traj, diagnostics)`` from the core; mu0 an (n, dim) float64 array, or a list of
        dim plain numbers (one state; None where the list holds anything else)."""
        body = self.body
        if isinstance(body, RigidBody):
            return _core.rollout_classical(  # type: ignore[no-any-return]
                self.name, body.inertia, mu0, h, n_steps, every, self.tol, self.max_iter, lazy
            )
        c, powers, coeffs = body.core_arrays()
        top = (
            (body.inertia, body.mgl, body.com)
            if isinstance(body, HeavyTop) and self.name == "splitting"
            else None
        )
        return _core.rollout_lie_poisson(  # type: ignore[no-any-return]
            self.name,
            c,
            powers,
            coeffs,
            mu0,
            h,
            n_steps,
            every,
            self.tol,
            self.max_iter,
            top,
            lazy,
        )

    def rollout(
        self, mu0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        body = self.body
        if self.name != "dop853":
            result = self._rust_rollout(mu0, h, n_steps, every, lazy=False)
            assert result is not None  # an array always gives one
            return result  # type: ignore[no-any-return]
        return dop853_rollout(body, mu0, h, n_steps, every, self.tol)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(name={self.name!r}, system={self.body!r}, "
            f"order={self.order}, poisson={self.poisson})"
        )


def _restore_classical(
    cls: type[ClassicalIntegrator], body: LiePoissonSystem, name: str, tol: float, max_iter: int
) -> ClassicalIntegrator:
    """Unpickles a :class:`ClassicalIntegrator` (see its ``__reduce__``)."""
    return cls(body, name, tol=tol, max_iter=max_iter)


def classical(
    system: Any, name: str, *, tol: float = NEWTON_TOL, max_iter: int = NEWTON_MAX_ITER
) -> Stepper:
    """A classical baseline integrator for any Poisson system, usable with :func:`integrate`.

    ``name`` is one of :func:`classical_methods` ``(system)``: on the rigid body "rk4",
    "midpoint", "splitting", "splitting4", "dmv", "splitting_casimir" (fixed step h, Rust) and
    "dop853" (adaptive, SciPy; h only spaces the output); "rk4", "midpoint", "dop853" on every
    system, plus each structure's own explicit Poisson splittings ("splitting" for the heavy
    top, "log_splitting" and "log_splitting4" for a log-canonical system). ``tol`` and
    ``max_iter`` set the implicit methods' Newton solve; for "dop853" ``tol`` is its rtol and
    atol. TypeError for a ``system`` that is not a Poisson system, ValueError for an unknown
    name (the message lists the valid ones).

    >>> import poisson_rs as pr
    >>> rk4 = pr.classical(pr.RigidBody(), "rk4")
    >>> pr.integrate(rk4, [1.0, 1.0, 2.0], h=0.1, n_steps=10).shape
    (11, 3)
    """
    system = as_system(system)
    names = system.classical_methods()
    if not (isinstance(name, str) and name in names):
        raise ValueError(
            f"unknown classical integrator {name!r} for {system!r}; valid names: {', '.join(names)}"
        )
    _check_newton(tol, max_iter)
    return system.classical(name, tol=tol, max_iter=max_iter)


# ---------------------------------------------------------------------------------------------
# Log-canonical structures (Lotka–Volterra): Taylor-HJ on the exact groupoid, classical baselines
# ---------------------------------------------------------------------------------------------


def _log_system(system: Any) -> Any:
    from .structures.log_canonical import LogCanonicalSystem

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
    return np.ascontiguousarray(np.log(x0))


def _exp_states(traj: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):
        return np.exp(traj)


class LogCanonicalTaylorIntegrator:
    """Taylor-HJ bisection integrator of a log-canonical system on its exact groupoid.

    S = Σ_{k≤order} t^k S_k with the S_k exact polynomials in y = e^q
    (:func:`poisson_rs.realizations.log_canonical.taylor_terms`); a step solves
    q + ½ c ∇S(q) = ln x_k by Newton in Rust and returns x_{k+1} = exp(q − ½ c ∇S(q)). Every
    monomial Casimir Σ k_i ln x_i is kept to round-off whatever the order. States are x > 0.
    Built by :func:`log_canonical_taylor`.
    """

    def __init__(
        self,
        system: Any,
        order: int = 3,
        *,
        tol: float = NEWTON_TOL,
        max_iter: int = NEWTON_MAX_ITER,
    ):
        from .realizations.log_canonical import taylor_arrays

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
    from .structures.log_canonical import LogCanonicalSystem

    return cls(LogCanonicalSystem.from_dict(data), order, tol=tol, max_iter=max_iter)


class _LearnedRealizationIntegrator:
    """What the learned S of every non-Lie–Poisson realization shares: the model file read
    once (bytes kept for pickling), ``tol`` and ``max_iter`` checked, the core's model, and the
    properties and pickling built on them. A subclass reads its file (:meth:`_load`) and rolls
    out (:meth:`rollout`)."""

    _default_name = "learned"

    def __init__(self, source: Path | bytes, *, tol: float, max_iter: int) -> None:
        if not (isinstance(tol, numbers.Real) and 0 < tol < 1):
            raise ValueError(f"tol must lie in (0, 1), got {tol!r}")
        if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
            raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")
        if isinstance(source, bytes):
            data, where = source, "model bytes"
        else:
            check_input_file(source, max_bytes=MAX_MODEL_BYTES, what="model file")
            data, where = Path(source).read_bytes(), f"model file {source}"
        self._bytes = data
        self.metadata, self._core = self._load(data, where)
        self.system = self.metadata["system"]
        self.h_max = float(self.metadata["h_max"])
        self.domain: dict[str, Any] = self.metadata["domain"]
        self.name = str(self.metadata.get("name", self._default_name))
        self.tol = float(tol)
        self.max_iter = int(max_iter)

    def _load(self, data: bytes, where: str) -> tuple[dict[str, Any], Any]:
        raise NotImplementedError

    @property
    def dim(self) -> int:
        return int(self._core.dim)

    @property
    def n_parameters(self) -> int:
        return int(self._core.n_parameters)

    @property
    def mlp_power(self) -> int:
        return int(self._core.mlp_power)

    @property
    def taylor_order(self) -> int:
        return int(self.metadata["taylor_order"])

    def __reduce__(self) -> tuple[Any, ...]:
        return (_restore_learned, (type(self), self._bytes, self.tol, self.max_iter))

    def derivatives(self, t: float, x: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """S, ∇S and ∇²S at time t for x (n, dim) in the core's coordinates, from Rust."""
        arr = np.ascontiguousarray(np.asarray(x, dtype=np.float64).reshape(-1, self.dim))
        return self._core.derivatives(float(t), arr)  # type: ignore[no-any-return]

    def _describe(self) -> str:
        return f"taylor_order={self.taylor_order}"

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(name={self.name!r}, {self._describe()}, "
            f"mlp_power={self.mlp_power}, parameters={self.n_parameters}, system={self.system!r})"
        )


def _restore_learned(
    cls: type[_LearnedRealizationIntegrator], data: bytes, tol: float, max_iter: int
) -> _LearnedRealizationIntegrator:
    return cls(data, tol=tol, max_iter=max_iter)


class LearnedLogCanonicalIntegrator(_LearnedRealizationIntegrator):
    """A learned generating function on the exact log-canonical groupoid, read from a model file
    whose metadata says ``structure = log_canonical``
    (:mod:`poisson_rs.realizations.log_canonical_hj`): S(t, q) = exact Taylor terms +
    t^m·MLP(t, q) in q = ln x. A step solves q + ½ c ∇S(h, q) = ln x_k by full Newton in Rust
    (|δ|∞ ≤ tol · max(|q|∞, 1)) and returns x_{k+1} = exp(q − ½ c ∇S(h, q)): a Poisson map that
    keeps every monomial Casimir to round-off whatever the network learned. States are x > 0.
    Built by :func:`load_model`.
    """

    _default_name = "learned-log-canonical"

    def __init__(
        self, source: Path | bytes, *, tol: float = NEWTON_TOL, max_iter: int = NEWTON_MAX_ITER
    ) -> None:
        super().__init__(source, tol=tol, max_iter=max_iter)

    def _load(self, data: bytes, where: str) -> tuple[dict[str, Any], Any]:
        with parsing(where):
            core = _core.LogCanonicalModel.from_bytes(data)
        metadata = parse_log_canonical_metadata(core.metadata, where)
        system = metadata["system"]
        with parsing(where, "system"):
            if system.dim != core.dim or not np.array_equal(system.c, core.c):
                raise ValueError(
                    f"metadata 'system' ({system!r}) does not match the file's structure.c"
                )
        return metadata, core

    def rollout(
        self, mu0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        q, info = self._core.rollout(_positive_log(mu0), h, n_steps, every, self.tol, self.max_iter)
        return _exp_states(q), info


class LearnedPolynomialIntegrator(_LearnedRealizationIntegrator):
    """A learned generating function on the order-n approximate realization of a polynomial
    bivector, read from a model file whose metadata says ``structure = polynomial``
    (:mod:`poisson_rs.realizations.polynomial_hj`): S(t, x) = exact Taylor-HJ terms of order m +
    t^M·MLP(t, x). A step solves α(x, ∇S(h, x)) = x_k by full Newton in Rust
    (|δ|∞ ≤ tol · max(|x|∞, 1)) and returns β(x, ∇S(h, x)). The realization is Poisson only to
    order n, so the Casimirs drift by O(h^{n+1}) a step (O(h^{n+2}) for odd n) whatever the
    network learned. Built by :func:`load_model`.
    """

    _default_name = "learned-polynomial"

    def __init__(
        self, source: Path | bytes, *, tol: float = NEWTON_TOL, max_iter: int = NEWTON_MAX_ITER
    ) -> None:
        super().__init__(source, tol=tol, max_iter=max_iter)

    def _load(self, data: bytes, where: str) -> tuple[dict[str, Any], Any]:
        from .realizations.polynomial_hj import read_model_file

        return read_model_file(data, where)  # type: ignore[no-any-return]

    @property
    def realization_order(self) -> int:
        return int(self.metadata["realization_order"])

    def _describe(self) -> str:
        return f"taylor_order={self.taylor_order}, realization_order={self.realization_order}"

    def rollout(
        self, mu0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        arr = np.ascontiguousarray(mu0, dtype=np.float64)
        return self._core.rollout(arr, h, n_steps, every, self.tol, self.max_iter)  # type: ignore[no-any-return]


#: Order of accuracy and whether a step is a Poisson map, for the classical integrators of a
#: log-canonical system.
LOG_CANONICAL_METHODS: dict[str, tuple[int, bool]] = {
    "rk4": (4, False),
    "midpoint": (2, False),
    "log_splitting": (2, True),
    "log_splitting4": (4, True),
    "dop853": (8, False),
}


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
    from .structures.log_canonical import LogCanonicalSystem

    return cls(LogCanonicalSystem.from_dict(data), name, tol=tol, max_iter=max_iter)


def log_canonical_taylor(
    system: Any, order: int = 3, *, tol: float = NEWTON_TOL, max_iter: int = NEWTON_MAX_ITER
) -> LogCanonicalTaylorIntegrator:
    """The Taylor-HJ integrator of order ``order`` for a log-canonical system (e.g.
    :func:`~poisson_rs.lotka_volterra`), usable with :func:`integrate`. Its order of accuracy is
    ``order + 1`` for odd ``order`` (the even Taylor terms vanish) and ``order`` otherwise.

    >>> import poisson_rs as pr
    >>> lv = pr.lotka_volterra([[0, 1], [-1, 0]], [1, 2])
    >>> pr.integrate(pr.log_canonical_taylor(lv, 3), [1.0, 0.8], h=0.1, n_steps=10).shape
    (11, 2)
    """
    return LogCanonicalTaylorIntegrator(system, order, tol=tol, max_iter=max_iter)


def log_canonical_classical(
    system: Any, name: str, *, tol: float = NEWTON_TOL, max_iter: int = NEWTON_MAX_ITER
) -> LogCanonicalClassicalIntegrator:
    """A classical baseline ("rk4", "midpoint", "log_splitting", "log_splitting4", "dop853")
    for a log-canonical system; see :class:`LogCanonicalClassicalIntegrator`."""
    return LogCanonicalClassicalIntegrator(system, name, tol=tol, max_iter=max_iter)
