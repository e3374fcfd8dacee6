"""Learned generating functions on a structure's realization other than T*G: the log-canonical
groupoid and the order-n realization of a polynomial bivector, read from model files."""

from __future__ import annotations

import numbers
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .. import _core
from ..export import check_widths, parse_log_canonical_metadata, read_tensor, terms_agree
from ..files import check_input_file
from ..protocols import NEWTON_MAX_ITER, NEWTON_TOL
from ..untrusted import InputError, parsing
from .log_canonical import _exp_states, _positive_log

#: Largest model file read (the paper's 253k-parameter model takes 2 MB).
MAX_MODEL_BYTES = 1 << 30


class _LearnedRealizationIntegrator:
    """What the learned S of every non-Lie–Poisson realization shares: the model file read
    once (bytes kept for pickling), ``tol`` and ``max_iter`` checked, the core's model, and the
    properties and pickling built on them. A subclass reads its file (:meth:`_load`) and rolls
    out (:meth:`rollout`)."""

    _bytes: bytes
    _source: Any
    _core: Any
    metadata: dict[str, Any]
    system: Any
    h_max: float
    name: str
    tol: float
    max_iter: int

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

    def save(self, path: str | os.PathLike[str], *, overwrite: bool = False) -> Path:
        """Writes the model file (the bytes it was built from) to ``path``, atomically; an
        existing file is kept (ValueError naming the path) unless ``overwrite``. Returns the
        path; :func:`~poisson_rs.load_model` reads it back to the same steps, bit for bit."""
        from ..files import atomic_write_bytes

        return atomic_write_bytes(path, self._bytes, replace=bool(overwrite))

    def __reduce__(self) -> tuple[Any, ...]:
        return (_restore_learned, (type(self), self._bytes, self.tol, self.max_iter))

    def derivatives(self, t: float, x: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """S, ∇S and ∇²S at time t for x (n, dim) in the core's coordinates, from Rust."""
        arr = np.ascontiguousarray(np.asarray(x, dtype=np.float64).reshape(-1, self.dim))
        return self._core.derivatives(float(t), arr)

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
    t^m·MLP(t, q) in q = ln x. A step solves q + ½ c ∇S(h, q) = ln x_k by Newton in Rust
    (|δ|∞ ≤ tol · max(|q|∞, 1); started from the Taylor terms' q_k − ½ c ∇S(q_k), the t^m-small
    network term's Hessian taken at the first update and kept) and returns
    x_{k+1} = exp(q − ½ c ∇S(h, q)): a Poisson map that
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
            core = _core.LearnedModel.from_log_canonical_bytes(data)
        metadata = parse_log_canonical_metadata(core.metadata, where)
        system = metadata["system"]
        c = read_tensor(data, "structure.c")  # checked by the core: (N, N), finite
        with parsing(where, "system"):
            if system.dim != core.dim or c is None or not np.array_equal(system.c, c):
                raise ValueError(
                    f"metadata 'system' ({system!r}) does not match the file's structure.c"
                )
        check_widths(data, metadata["widths"], where)
        _check_log_taylor_terms(data, metadata, where)
        return metadata, core

    def rollout(
        self, mu0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        q, info = self._core.rollout(_positive_log(mu0), h, n_steps, every, self.tol, self.max_iter)
        return _exp_states(q), info


#: Highest Taylor order a log-canonical model file may state (that of its training config).
MAX_LOG_TAYLOR_ORDER = 9


def _check_log_taylor_terms(data: bytes, metadata: dict[str, Any], where: str) -> None:
    """InputError unless the file's exact Taylor terms (``poly.powers``, ``poly.coeffs``,
    ``poly.linear``) are S_1..S_K of the system its metadata records, K its ``taylor_order``.
    The terms are what the core steps; ``system`` is what a study scores against, so a file
    whose metadata names another H would integrate one system and report another. S_1 = −H
    (the t¹ rows and the log part) names ``system``; the rest names ``taylor_order``."""
    from ..realizations.log_canonical import taylor_arrays

    system = metadata["system"]
    order = metadata["taylor_order"]
    powers, coeffs, linear = (
        read_tensor(data, k) for k in ("poly.powers", "poly.coeffs", "poly.linear")
    )
    if powers is None or coeffs is None or linear is None:  # the core requires all three
        raise InputError(where, "tensors", "the file lacks its Taylor terms")
    with parsing(where, "system"):
        tp, ex, co = taylor_arrays(system, 1)
        first = powers[:, 0] == 1
        b = np.asarray(system.log_hamiltonian.b, dtype=np.float64)
        if not (
            terms_agree((powers[first], coeffs[first]), (np.c_[tp, ex], co))
            and terms_agree(
                (np.eye(len(b), dtype=np.int64), linear), (np.eye(len(b), dtype=np.int64), b)
            )
        ):
            raise ValueError(
                f"the file's t¹ terms are not -t·H of the system its metadata records "
                f"({system!r}): the metadata was edited or belongs to another model"
            )
    with parsing(where, "taylor_order"):
        # The Taylor terms' cost grows fast with the order: a stated order is bounded first.
        if not 1 <= order <= MAX_LOG_TAYLOR_ORDER:
            raise ValueError(
                f"metadata 'taylor_order' must be in 1..={MAX_LOG_TAYLOR_ORDER}, got {order}"
            )
        tp, ex, co = taylor_arrays(system, order)
        if not terms_agree((powers, coeffs), (np.c_[tp, ex], co)):
            raise ValueError(
                f"metadata 'taylor_order' says {order} but the file's Taylor terms are not "
                f"S_1..S_{order} of its system"
            )


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
        from ..realizations.polynomial_hj import read_model_file

        return read_model_file(data, where)

    @property
    def realization_order(self) -> int:
        return int(self.metadata["realization_order"])

    def _describe(self) -> str:
        return f"taylor_order={self.taylor_order}, realization_order={self.realization_order}"

    def rollout(
        self, mu0: np.ndarray, h: float, n_steps: int, every: int
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        arr = np.ascontiguousarray(mu0, dtype=np.float64)
        return self._core.rollout(arr, h, n_steps, every, self.tol, self.max_iter)
