"""Model files: the bisection integrators read from a file or bytes (a learned S, or the exact
Taylor terms of a Lie–Poisson system), the shipped models, and the checks that tie a file's
metadata to its tensors."""

from __future__ import annotations

import copy
import math
import numbers
import os
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from . import _core
from .export import (
    DOMAIN_KINDS,
    load_generating,
    model_structure,
    parse_metadata,
    read_tensor,
)
from .files import check_input_file
from .protocols import (
    NEWTON_MAX_ITER,
    NEWTON_TOL,
)
from .realizations.lie_groupoid import sou
from .structures.lie_poisson import LiePoissonSystem
from .untrusted import parsing

if TYPE_CHECKING:
    import torch

    from .generating import GeneratingFunction
from .rollout import (
    _as_states,
    _check_step,
    _check_time,
)
from .steppers.learned_realization import (
    MAX_MODEL_BYTES,
    LearnedLogCanonicalIntegrator,
    LearnedPolynomialIntegrator,
)

MODELS_PACKAGE = "poisson_rs.models"


DEFAULT_MODEL = "default"


class BisectionIntegrator:
    """A Poisson integrator read off the Lagrangian bisection of a generating function S(t, p).

    Steps run in the Rust core; :meth:`torch_step` is the same map in pure torch, for checking.
    Build one with :func:`load_model` (a learned S saved to a file) or :func:`taylor_integrator`
    (the truncated Taylor series of the exact S).
    """

    _source: Path | bytes
    _bytes: bytes
    _core: Any
    tol: float
    max_iter: int
    newton: str

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
        return self.metadata["system"]

    @property
    def dim(self) -> int:
        """Dimension of the system's phase space g*."""
        return int(self._core.dim)

    @property
    def body(self) -> LiePoissonSystem:
        """An alias of :attr:`system`, kept one release for the rigid-body models that used it
        (every model answers it now)."""
        return self.system

    def save(self, path: str | os.PathLike[str], *, overwrite: bool = False) -> Path:
        """Writes the model file (the bytes it was built from) to ``path``, atomically; an
        existing file is kept (ValueError naming the path) unless ``overwrite``. Returns the
        path; :func:`~poisson_rs.load_model` reads it back to the same steps, bit for bit."""
        from .files import atomic_write_bytes

        return atomic_write_bytes(path, self._bytes, replace=bool(overwrite))

    @property
    def step_h(self) -> float | None:
        """The one step size a learned time-h map steps at (its file's ``step_h``), or None
        for a generating function valid for every t up to :attr:`h_max`."""
        value = self.metadata.get("step_h")
        return None if value is None else float(value)

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
            name = f"model file {self.path}" if self.path is not None else "model bytes"
            with parsing(name):
                tensors = load(self._bytes)
                self._generating = load_generating(tensors, self.metadata)
        return self._generating

    def torch_step(self, mu: torch.Tensor, h: float) -> torch.Tensor:
        """The step map in pure torch (autograd Newton), float64, on mu's device (the device
        rollouts' :func:`~poisson_rs.on_device`). mu: (B, n) → (B, n)."""
        import torch

        from .generating import bisection_step

        step = _check_step(h)
        mu = torch.as_tensor(mu, dtype=torch.float64)
        generating = self.generating
        if mu.device != torch.device("cpu"):
            # A copy per device: Module.to() moves in place, and the CPU module stays the oracle.
            on = self.__dict__.setdefault("_generating_on", {})
            if mu.device not in on:
                on[mu.device] = copy.deepcopy(generating).to(mu.device)
            generating = on[mu.device]
        return bisection_step(
            generating, mu, step, chart=self.chart, tol=self.tol, max_iter=self.max_iter
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


def shipped_models(system: Any) -> dict[str, Any]:
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
        if first is not None and powers is not None and coeffs is not None and first.any():
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
