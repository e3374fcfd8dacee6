"""Lie–Poisson systems on the dual g* of a finite-dimensional Lie algebra g.

A Lie algebra is given by its structure constants, [e_i, e_j] = Σ_k c[i,j,k] e_k, and a system by
a polynomial Hamiltonian H on g* ≅ Rⁿ. The dynamics follow the rigid body's convention (on so(3),
c = ε, they read μ̇ = μ × ∇H):

    μ̇_j = Σ_{i,k} c[i,j,k] ∂H/∂μ_i μ_k = (ad_{∇H}ᵀ μ)_j,   with (ad_x)_{kj} = Σ_i c[i,j,k] x_i.

Named systems: :class:`RigidBody` on so(3)* (H = ½ Σ μᵢ²/Iᵢ) and :class:`HeavyTop` on se(3)*
(μ = (M, Γ), H = ½ Σ Mᵢ²/Iᵢ + mgl χ·Γ). Units are the caller's: μ is a momentum, H an energy, and
time is whatever unit makes μ̇ = {μ, H} consistent with them.

Every class evaluates on NumPy arrays and, differentiably, on torch tensors; torch is imported only
when a tensor arrives.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..protocols import BracketTerms, JetRealization, PoissonSystemBase
from ..untrusted import parsing

__all__ = ["HeavyTop", "LieAlgebra", "LiePoissonSystem", "Polynomial", "RigidBody"]

FloatArray = NDArray[np.float64]

#: Largest algebra dimension accepted (the Jacobi check costs n⁵).
MAX_DIM = 10
#: Largest total degree of a Hamiltonian polynomial.
MAX_DEGREE = 12


# --- helpers -------------------------------------------------------------------------------------


def _scaled(value: float, scale: float, power: int) -> str:
    """value · scale**power, formatted for a message without overflowing float64 (a huge algebra's
    scale squared does not fit)."""
    if value == 0:
        return "0"
    log10 = math.log10(abs(value)) + power * math.log10(scale)
    exponent = math.floor(log10)
    return f"{math.copysign(10 ** (log10 - exponent), value):.3f}e{exponent:+d}"


def _is_tensor(x: object) -> bool:
    return type(x).__module__.partition(".")[0] == "torch"


def _as_states(mu: Any, n: int, name: str = "mu") -> Any:
    """``mu`` as a float64 array, or a floating torch tensor, of shape (..., n); else ValueError."""
    if _is_tensor(mu):
        if mu.ndim == 0 or mu.shape[-1] != n:
            raise ValueError(f"{name} must have shape (..., {n}), got shape {tuple(mu.shape)}")
        if mu.is_complex():
            raise ValueError(f"{name} must be real, got a complex tensor")
        return mu if mu.is_floating_point() else mu.double()
    if np.iscomplexobj(mu):
        raise ValueError(f"{name} must be an array of real numbers, got complex values")
    try:
        arr = np.asarray(mu, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be an array of real numbers") from exc
    if arr.ndim == 0 or arr.shape[-1] != n:
        raise ValueError(f"{name} must have shape (..., {n}), got shape {arr.shape}")
    return arr


def _constant(xp_like: Any, values: FloatArray) -> Any:
    """``values`` as a tensor matching ``xp_like`` (dtype, device), or unchanged for NumPy."""
    if _is_tensor(xp_like):
        import torch

        # A copy (torch.tensor): the constants are read-only arrays.
        return torch.tensor(values, dtype=xp_like.dtype, device=xp_like.device)
    return values


def _einsum(like: Any, spec: str, *operands: Any) -> Any:
    if _is_tensor(like):
        import torch

        return torch.einsum(spec, *operands)
    return np.einsum(spec, *operands)


def _real(value: object, what: str) -> float:
    """A finite real number that is not a bool, as float; else ValueError naming ``what``."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real):
        raise ValueError(f"{what} must be a real number, got {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise ValueError(f"{what} must be finite, got {out}")
    return out


def _real_triple(raw: object, what: str) -> tuple[float, float, float]:
    """Three real numbers (no bools) as floats; finiteness is checked by the caller's rules."""
    try:
        entries = tuple(raw)  # type: ignore[call-overload]
    except TypeError as exc:
        raise ValueError(f"{what} must be a sequence of 3 real numbers, got {raw!r}") from exc
    if len(entries) != 3:
        raise ValueError(f"{what} must have exactly 3 entries, got {len(entries)}")
    if any(isinstance(v, bool | np.bool_) for v in entries):
        raise ValueError(f"{what} entries must be real numbers, not booleans, got {raw!r}")
    if not all(isinstance(v, numbers.Real) for v in entries):
        raise ValueError(f"{what} entries must be real numbers, got {raw!r}")
    return tuple(float(v) for v in entries)  # type: ignore[return-value]


def _inertia(raw: object) -> tuple[float, float, float]:
    """Principal moments of inertia: 3 finite, strictly positive reals."""
    values = _real_triple(raw, "inertia")
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"inertia entries must be finite, got {values}")
    if not all(v > 0.0 for v in values):
        raise ValueError(f"inertia entries must be strictly positive, got {values}")
    return values


def _levi_civita() -> FloatArray:
    eps = np.zeros((3, 3, 3))
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        eps[i, j, k], eps[j, i, k] = 1.0, -1.0
    return eps


_EPS = _levi_civita()
_EPS.flags.writeable = False


def _frozen(self: object, name: str, value: object) -> None:
    raise AttributeError(f"{type(self).__name__} is immutable; cannot set {name!r}")


# --- Lie algebras --------------------------------------------------------------------------------


def linear_bracket_terms(c: ArrayLike, cocycle: ArrayLike | None = None) -> BracketTerms:
    """{x_i, x_j} = −Σ_k c[i,j,k] x_k + ω_ij as polynomial entries (i < j)."""
    c = np.asarray(c, dtype=np.float64)
    n = c.shape[0]
    terms: list[tuple[int, int, list[int], float]] = []
    for i in range(n):
        for j in range(i + 1, n):
            for k in range(n):
                e = [0] * n
                e[k] = 1
                terms.append((i, j, e, -float(c[i, j, k])))
            if cocycle is not None:
                terms.append((i, j, [0] * n, float(np.asarray(cocycle)[i, j])))
    return BracketTerms.from_terms(n, terms)


class LieAlgebra:
    """A real Lie algebra of dimension n by its structure constants.

    Parameters
    ----------
    c : array_like, shape (n, n, n), 1 ≤ n ≤ 10
        [e_i, e_j] = Σ_k c[i,j,k] e_k. Must be real and finite, antisymmetric in (i, j) and obey
        the Jacobi identity, both to 1e-12 relative to max|c| (max|c|² for Jacobi).
    name : str, optional
        A label; equality and hashing ignore it.

    Attributes
    ----------
    c : ndarray, float64, shape (n, n, n), read-only
    dim : int
    name : str or None
    """

    __slots__ = ("_c", "_name")
    __setattr__ = _frozen
    __delattr__ = _frozen  # type: ignore[assignment]

    def __init__(self, c: ArrayLike, name: str | None = None) -> None:
        if name is not None and not isinstance(name, str):
            raise ValueError(f"name must be a string or None, got {name!r}")
        object.__setattr__(self, "_c", _check_structure_constants(c))
        object.__setattr__(self, "_name", name)

    @classmethod
    def so3(cls) -> LieAlgebra:
        """so(3): c = ε, the Levi-Civita symbol ([e_i, e_j] = ε_ijk e_k)."""
        return cls(_EPS, name="so3")

    @classmethod
    def se3(cls) -> LieAlgebra:
        """se(3) in the basis (R₁, R₂, R₃, T₁, T₂, T₃): [R_i, R_j] = ε_ijk R_k,
        [R_i, T_j] = ε_ijk T_k, [T_i, T_j] = 0."""
        c = np.zeros((6, 6, 6))
        c[:3, :3, :3] = _EPS
        c[:3, 3:, 3:] = _EPS
        c[3:, :3, 3:] = -_EPS.transpose(1, 0, 2)
        return cls(c, name="se3")

    @classmethod
    def sl2(cls) -> LieAlgebra:
        """sl(2, R) in the basis (h, e, f): [h, e] = 2e, [h, f] = −2f, [e, f] = h."""
        c = np.zeros((3, 3, 3))
        for i, j, k, v in ((0, 1, 1, 2.0), (0, 2, 2, -2.0), (1, 2, 0, 1.0)):
            c[i, j, k], c[j, i, k] = v, -v
        return cls(c, name="sl2")

    @property
    def c(self) -> FloatArray:
        return self._c

    @property
    def dim(self) -> int:
        return int(self._c.shape[0])

    @property
    def name(self) -> str | None:
        return self._name

    def is_so3(self) -> bool:
        """True when c is exactly the Levi-Civita symbol (the closed-form so(3) charts apply)."""
        return self._c.shape == (3, 3, 3) and bool(np.array_equal(self._c, _EPS))

    def ad(self, x: Any) -> Any:
        """ad_x as a matrix, (ad_x)_{kj} = Σ_i c[i,j,k] x_i, so that ad_x e_j = [x, e_j].

        Parameters
        ----------
        x : array_like or torch.Tensor, shape (..., n)

        Returns
        -------
        ndarray or torch.Tensor, shape (..., n, n)
        """
        x = _as_states(x, self.dim, "x")
        return _einsum(x, "ijk,...i->...kj", _constant(x, self._c), x)

    def ad_transpose(self, x: Any) -> Any:
        """ad_xᵀ, (ad_xᵀ)_{jk} = Σ_i c[i,j,k] x_i: the coadjoint action up to sign.

        Parameters
        ----------
        x : array_like or torch.Tensor, shape (..., n)

        Returns
        -------
        ndarray or torch.Tensor, shape (..., n, n)
        """
        return self.ad(x).swapaxes(-1, -2)

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form: {"name": str | None, "structure_constants": nested lists (n, n, n)}."""
        return {"name": self._name, "structure_constants": self._c.tolist()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> LieAlgebra:
        """Inverse of :meth:`to_dict`; one ValueError (InputError) on a malformed dictionary."""
        with parsing("Lie algebra dictionary"):
            if not isinstance(data, Mapping) or "structure_constants" not in data:
                raise ValueError("a Lie algebra dictionary needs a 'structure_constants' entry")
            return cls(data["structure_constants"], name=data.get("name"))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, LieAlgebra):
            return NotImplemented
        return self._c.shape == other._c.shape and bool(np.array_equal(self._c, other._c))

    def __hash__(self) -> int:
        # -0.0 was normalised to 0.0 on construction, so equal arrays have equal bytes.
        return hash((self._c.shape, self._c.tobytes()))

    def __reduce__(self) -> tuple[Any, ...]:
        return (LieAlgebra, (self._c, self._name))

    def __repr__(self) -> str:
        return f"LieAlgebra(dim={self.dim}, name={self._name!r})"


def _check_structure_constants(c: ArrayLike) -> FloatArray:
    """Validated, read-only float64 copy of ``c``; ValueError naming the problem."""
    try:
        raw = np.asarray(c)
    except (TypeError, ValueError) as exc:
        raise ValueError("structure constants must be an array of real numbers") from exc
    if raw.dtype.kind == "b":
        raise ValueError("structure constants must be real numbers, not booleans")
    if raw.dtype.kind == "c":
        raise ValueError("structure constants must be real, got complex values")
    try:
        arr = np.array(raw, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError("structure constants must be an array of real numbers") from exc
    n = arr.shape[0] if arr.ndim else 0
    if arr.ndim != 3 or arr.shape != (n, n, n):
        raise ValueError(f"structure constants must have shape (n, n, n), got shape {arr.shape}")
    if not 1 <= n <= MAX_DIM:
        raise ValueError(f"the algebra's dimension must be between 1 and {MAX_DIM}, got {n}")
    if not np.isfinite(arr).all():
        raise ValueError("structure constants must be finite (found NaN or inf)")
    # Both checks on c / max(max|c|, 1): the Jacobi sums are quadratic in c and would overflow
    # (and so pass) for |c| > 1e154.
    scale = max(1.0, float(np.max(np.abs(arr))))
    unit = arr / scale
    skew = np.abs(unit + unit.transpose(1, 0, 2))
    if skew.max() > 1e-12:
        i, j, k = np.unravel_index(int(np.argmax(skew)), skew.shape)
        if i == j:
            raise ValueError(
                f"structure constants are not antisymmetric: [e_i, e_i] = 0 needs "
                f"c[i,i,k] = 0, but c[{i},{i},{k}] = {float(arr[i, j, k])!r}"
            )
        raise ValueError(
            f"structure constants are not antisymmetric: [e_i, e_j] = -[e_j, e_i] needs "
            f"c[i,j,k] = -c[j,i,k], but c[{i},{j},{k}] = {float(arr[i, j, k])!r} and "
            f"c[{j},{i},{k}] = {float(arr[j, i, k])!r}"
        )
    # Jacobi: Σ_l c[i,j,l] c[l,k,m] + c[j,k,l] c[l,i,m] + c[k,i,l] c[l,j,m] = 0.
    a = np.einsum("ijl,lkm->ijkm", unit, unit)
    jacobi = np.abs(a + a.transpose(1, 2, 0, 3) + a.transpose(2, 0, 1, 3))
    if jacobi.max() > 1e-12:
        i, j, k, m = np.unravel_index(int(np.argmax(jacobi)), jacobi.shape)
        raise ValueError(
            f"structure constants violate the Jacobi identity "
            f"[e_i,[e_j,e_k]] + [e_j,[e_k,e_i]] + [e_k,[e_i,e_j]] = 0 at (e{i}, e{j}, e{k}), "
            f"component {m}: {_scaled(float(jacobi[i, j, k, m]), float(scale), 2)}"
        )
    arr += 0.0  # -0.0 → 0.0, for hashing by bytes
    arr.flags.writeable = False
    return arr


# --- polynomials ---------------------------------------------------------------------------------


class Polynomial:
    """A real polynomial on Rⁿ, Σ_m a_m μ^{e_m}, with μ^e = Π_i μ_i^{e_i}.

    Parameters
    ----------
    coefficients : Mapping[tuple[int, ...], float]
        Exponent tuples (all of one length n ≥ 1, non-negative ints, not bools) to finite real
        coefficients, e.g. ``{(2, 0, 0): 1/3, (0, 2, 0): 1/4, (0, 0, 2): 1/5}``. Zero coefficients
        are dropped (a lone zero term gives the zero polynomial on Rⁿ). Degree at most 12.

    Attributes
    ----------
    dim : int
        n, the number of variables.
    degree : int
        Largest total degree of a term (0 for the zero polynomial).
    terms : Mapping[tuple[int, ...], float]
        Read-only, sorted by total degree, then exponents.
    """

    __slots__ = ("_dcoeffs", "_degree", "_dim", "_dpowers", "_dvar", "_powers", "_terms")
    __setattr__ = _frozen
    __delattr__ = _frozen  # type: ignore[assignment]

    def __init__(self, coefficients: Mapping[tuple[int, ...], float]) -> None:
        if not isinstance(coefficients, Mapping):
            raise ValueError(
                "coefficients must be a mapping from exponent tuples to real coefficients, "
                f"got {type(coefficients).__name__}"
            )
        if not coefficients:
            raise ValueError(
                "a polynomial needs at least one term (a zero one fixes the dimension)"
            )
        dims = set()
        terms: dict[tuple[int, ...], float] = {}
        for key, value in coefficients.items():
            if not isinstance(key, tuple):
                raise ValueError(f"exponents must be tuples of ints, got {key!r}")
            if any(
                isinstance(e, bool | np.bool_) or not isinstance(e, numbers.Integral) for e in key
            ):
                raise ValueError(f"exponents must be non-negative ints, got {key!r}")
            exps = tuple(int(e) for e in key)
            if any(e < 0 for e in exps):
                raise ValueError(f"exponents must be non-negative ints, got {key!r}")
            if sum(exps) > MAX_DEGREE:
                raise ValueError(f"term {key!r} has degree {sum(exps)} > {MAX_DEGREE}")
            dims.add(len(exps))
            coeff = _real(value, f"the coefficient of {key!r}")
            if coeff != 0.0:
                terms[exps] = terms.get(exps, 0.0) + coeff
        if len(dims) != 1:
            raise ValueError(f"exponent tuples must all have the same length, got lengths {dims}")
        (n,) = dims
        if n < 1:
            raise ValueError("exponent tuples must have at least one entry")
        ordered = dict(sorted(terms.items(), key=lambda kv: (sum(kv[0]), kv[0])))
        powers = np.array(list(ordered), dtype=np.int64).reshape(len(ordered), n)
        coeffs = np.array(list(ordered.values()), dtype=np.float64)
        # ∂/∂μ_j of every term with e_j > 0, flattened: exponents e − δ_j, coefficient a·e_j.
        rows, cols = np.nonzero(powers)
        dpowers = powers[rows].copy()
        dpowers[np.arange(rows.size), cols] -= 1
        for name, value in (
            ("_terms", MappingProxyType(ordered)),
            ("_dim", n),
            ("_degree", int(powers.sum(1).max(initial=0))),
            ("_powers", (powers, coeffs)),
            ("_dpowers", dpowers),
            ("_dcoeffs", coeffs[rows] * powers[rows, cols]),
            ("_dvar", cols),
        ):
            object.__setattr__(self, name, value)

    @classmethod
    def quadratic_diagonal(cls, weights: ArrayLike) -> Polynomial:
        """½ Σ wᵢ μᵢ² for finite real weights w (shape (n,)), e.g. w = 1/I for a rigid body."""
        w = np.asarray(weights)
        if w.ndim != 1 or w.size == 0:
            raise ValueError(f"weights must be a non-empty 1-D sequence, got shape {w.shape}")
        n = w.size
        return cls(
            {
                tuple(2 if j == i else 0 for j in range(n)): 0.5 * _real(v, f"weights[{i}]")
                for i, v in enumerate(w.tolist())
            }
        )

    @classmethod
    def from_arrays(cls, powers: ArrayLike, coeffs: ArrayLike) -> Polynomial:
        """From ``powers`` int (m, n) and ``coeffs`` float (m,); repeated rows are summed."""
        pw, cf = np.asarray(powers), np.asarray(coeffs)
        if pw.ndim != 2 or cf.shape != (pw.shape[0],):
            raise ValueError(
                f"powers must have shape (m, n) and coeffs (m,), got {pw.shape} and {cf.shape}"
            )
        if pw.dtype.kind not in "iu":
            raise ValueError(f"powers must be integers, got dtype {pw.dtype}")
        out: dict[tuple[int, ...], float] = {}
        for row, a in zip(pw.tolist(), cf.tolist(), strict=True):
            out[tuple(row)] = out.get(tuple(row), 0.0) + _real(a, f"the coefficient of {row}")
        if not out:
            raise ValueError("a polynomial needs at least one term")
        return cls(out)

    @property
    def dim(self) -> int:
        return self._dim

    @property
    def degree(self) -> int:
        return self._degree

    @property
    def terms(self) -> Mapping[tuple[int, ...], float]:
        return self._terms

    def to_arrays(self) -> tuple[NDArray[np.int64], FloatArray]:
        """(powers int64 (m, n), coeffs float64 (m,)), copies, in the order of :attr:`terms`."""
        powers, coeffs = self._powers
        return powers.copy(), coeffs.copy()

    def is_homogeneous(self, degree: int) -> bool:
        """True when every term has total degree ``degree`` (so also for the zero polynomial)."""
        return all(sum(e) == degree for e in self._terms)

    def _evaluate(self, mu: Any, powers: NDArray[np.int64], coeffs: FloatArray) -> Any:
        """The terms coeffs[m] μ^{powers[m]}, unsummed: (m, ...) for a validated mu (..., n)."""
        tensor = _is_tensor(mu)
        degree = int(powers.max(initial=0))
        # Integer powers by repeated products: exact for small integers, and autograd-friendly
        # (no 0**0 or 0**-1 in a pow backward).
        table = [mu.new_ones(mu.shape) if tensor else np.ones_like(mu)]
        for _ in range(degree):
            table.append(table[-1] * mu)
        if tensor:
            import torch

            stacked = torch.stack(table, 0)
            index = torch.as_tensor(powers, device=mu.device)
        else:
            stacked, index = np.stack(table, 0), powers
        mono = None
        for j in range(self._dim):
            factor = stacked[index[:, j], ..., j]  # (m, ...)
            mono = factor if mono is None else mono * factor
        return mono * _constant(mu, coeffs).reshape((-1,) + (1,) * (mu.ndim - 1))

    def __call__(self, mu: Any) -> Any:
        """P(μ). mu: (..., n) array or torch tensor (differentiable) → (...,)."""
        mu = _as_states(mu, self._dim)
        powers, coeffs = self._powers
        if coeffs.size == 0:
            return mu.sum(-1) * 0.0
        return self._evaluate(mu, powers, coeffs).sum(0)

    def gradient(self, mu: Any) -> Any:
        """∇P(μ), exact (term by term). mu: (..., n) array or torch tensor → (..., n)."""
        mu = _as_states(mu, self._dim)
        if self._dcoeffs.size == 0:
            return mu * 0.0
        terms = self._evaluate(mu, self._dpowers, self._dcoeffs)  # (m', ...)
        select = (self._dvar[None, :] == np.arange(self._dim)[:, None]).astype(np.float64)
        if _is_tensor(mu):
            import torch

            grad = torch.tensordot(_constant(mu, select), terms, dims=1)  # (n, ...)
            return torch.movedim(grad, 0, -1)
        return np.moveaxis(np.tensordot(select, terms, axes=1), 0, -1)

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form: {"dim": n, "terms": [[e₁, …, eₙ, coefficient], …]}."""
        return {"dim": self._dim, "terms": [[*e, a] for e, a in self._terms.items()]}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Polynomial:
        """Inverse of :meth:`to_dict`; one ValueError (InputError) on a malformed dictionary."""
        with parsing("polynomial dictionary"):
            return cls._from_dict(data)

    @classmethod
    def _from_dict(cls, data: Mapping[str, Any]) -> Polynomial:
        if not isinstance(data, Mapping) or "terms" not in data or "dim" not in data:
            raise ValueError("a polynomial dictionary needs 'dim' and 'terms' entries")
        n = data["dim"]
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"'dim' must be a positive int, got {n!r}")
        rows = data["terms"]
        if not isinstance(rows, list | tuple) or not all(
            isinstance(r, list | tuple) and len(r) == n + 1 for r in rows
        ):
            raise ValueError(f"'terms' must be a list of [e1, ..., e{n}, coefficient] rows")
        if not rows:
            return cls({(0,) * n: 0.0})
        return cls({tuple(r[:n]): r[n] for r in rows})

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Polynomial):
            return NotImplemented
        return self._dim == other._dim and dict(self._terms) == dict(other._terms)

    def __hash__(self) -> int:
        return hash((self._dim, tuple(self._terms.items())))

    def __reduce__(self) -> tuple[Any, ...]:
        return (Polynomial, (dict(self._terms) or {(0,) * self._dim: 0.0},))

    def __repr__(self) -> str:
        return f"Polynomial({dict(self._terms) or {(0,) * self._dim: 0.0}!r})"

    def formula(self, names: Sequence[str] | None = None) -> str:
        """The polynomial as text in the variables ``names`` (μ₁…μₙ by default), e.g.
        "μ₁² + μ₂² − 0.5 μ₃μ₄": coefficients to 4 significant digits, ±1 left out."""
        sup = str.maketrans("0123456789", "⁰¹²³⁴⁵⁶⁷⁸⁹")
        if names is None:
            sub = str.maketrans("0123456789", "₀₁₂₃₄₅₆₇₈₉")
            names = [f"μ{str(i).translate(sub)}" for i in range(1, self._dim + 1)]
        parts: list[tuple[str, str]] = []
        # By degree, then μ₁ before μ₂ (μ₁² + μ₂² + μ₃², not the stored order).
        ordered = sorted(self._terms.items(), key=lambda t: (sum(t[0]), [-e for e in t[0]]))
        for exps, coeff in ordered:
            mono = "".join(
                name + (str(e).translate(sup) if e > 1 else "")
                for name, e in zip(names, exps, strict=True)
                if e
            )
            size = f"{abs(coeff):.4g}"
            if mono and size == "1":
                text = mono
            else:
                text = f"{size} {mono}" if mono else size
            parts.append(("−" if coeff < 0 else "+", text))
        if not parts:
            return "0"
        sign, first = parts[0]
        out = ("−" if sign == "−" else "") + first
        return out + "".join(f" {sign} {text}" for sign, text in parts[1:])


# --- Lie–Poisson systems -------------------------------------------------------------------------


class LiePoissonSystem(PoissonSystemBase):
    """A Lie–Poisson system on g*: an algebra and a polynomial Hamiltonian H on g* ≅ Rⁿ.

    μ̇_j = Σ_{i,k} c[i,j,k] ∂H/∂μ_i μ_k (on so(3): μ̇ = μ × ∇H). Immutable, hashable; equality
    compares the kind, the algebra and H (not the name).

    Parameters
    ----------
    algebra : LieAlgebra
    hamiltonian : Polynomial
        H, with ``hamiltonian.dim == algebra.dim``.
    name : str, optional
    """

    kind: ClassVar[str] = "lie_poisson"
    __setattr__ = _frozen
    __delattr__ = _frozen  # type: ignore[assignment]

    def __init__(
        self, algebra: LieAlgebra, hamiltonian: Polynomial, name: str | None = None
    ) -> None:
        if not isinstance(algebra, LieAlgebra):
            raise TypeError(f"algebra must be a LieAlgebra, got {type(algebra).__name__}")
        if not isinstance(hamiltonian, Polynomial):
            raise TypeError(f"hamiltonian must be a Polynomial, got {type(hamiltonian).__name__}")
        if name is not None and not isinstance(name, str):
            raise ValueError(f"name must be a string or None, got {name!r}")
        self._init_system(algebra, hamiltonian, name)

    def _init_system(self, algebra: LieAlgebra, hamiltonian: Polynomial, name: str | None) -> None:
        if hamiltonian.dim != algebra.dim:
            raise ValueError(
                f"the Hamiltonian has {hamiltonian.dim} variables but the algebra has dimension "
                f"{algebra.dim}"
            )
        object.__setattr__(self, "_algebra", algebra)
        object.__setattr__(self, "_polynomial", hamiltonian)
        object.__setattr__(self, "_name", name)

    @property
    def algebra(self) -> LieAlgebra:
        return self._algebra  # type: ignore[attr-defined,no-any-return]

    @property
    def polynomial(self) -> Polynomial:
        """The Hamiltonian H as a :class:`Polynomial`."""
        return self._polynomial  # type: ignore[attr-defined,no-any-return]

    @property
    def name(self) -> str | None:
        return self._name  # type: ignore[attr-defined,no-any-return]

    @property
    def dim(self) -> int:
        return self.algebra.dim

    @property
    def component_names(self) -> tuple[str, ...]:
        """Names of the state's components, for tables and figures: (M₁, M₂, M₃, Γ₁, Γ₂, Γ₃) on
        se(3)*, (μ_h, μ_e, μ_f) on sl(2)*, else (μ₁, …, μₙ)."""
        kind = _known_algebra(self.algebra)
        if kind == "se3":
            return tuple(f"{b}{_subscript(i)}" for b in ("M", "Γ") for i in range(1, 4))
        if kind == "sl2":
            return ("μ_h", "μ_e", "μ_f")
        return tuple(f"μ{_subscript(i)}" for i in range(1, self.dim + 1))

    def _states(self, mu: Any) -> Any:
        return _as_states(mu, self.dim, "mu")

    def hamiltonian(self, mu: Any) -> Any:
        """H(μ). mu: (..., n) array or torch tensor (differentiable) → (...,)."""
        return self.polynomial(self._states(mu))

    def grad_hamiltonian(self, mu: Any) -> Any:
        """∇H(μ), exact. mu: (..., n) array or torch tensor → (..., n)."""
        return self.polynomial.gradient(self._states(mu))

    def poisson_tensor(self, mu: Any) -> Any:
        """Π(μ) with μ̇ = Π(μ) ∇H: Π_{ji} = Σ_k c[i,j,k] μ_k. mu: (..., n) → (..., n, n)."""
        mu = self._states(mu)
        return _einsum(mu, "ijk,...k->...ji", _constant(mu, self.algebra.c), mu)

    def vector_field(self, mu: Any) -> Any:
        """μ̇_j = Σ_{i,k} c[i,j,k] ∂H/∂μ_i μ_k. mu: (..., n) array or tensor → (..., n)."""
        mu = self._states(mu)
        grad = self.polynomial.gradient(mu)
        return _einsum(mu, "ijk,...i,...k->...j", _constant(mu, self.algebra.c), grad, mu)

    def casimirs(self, mu: Any) -> Any:
        """The known Casimirs at μ, or None when none is known for this algebra.

        so(3): |μ|²; se(3), μ = (M, Γ): (|Γ|², M·Γ); sl(2), μ = (μ_h, μ_e, μ_f): μ_h² + 4μ_eμ_f.

        Parameters
        ----------
        mu : array_like or torch.Tensor, shape (..., n)

        Returns
        -------
        ndarray or torch.Tensor, shape (..., m), or None
        """
        mu = self._states(mu)
        kind = _known_algebra(self.algebra)
        if kind is None:
            return None
        if kind == "so3":
            values = [(mu * mu).sum(-1)]
        elif kind == "se3":
            m, g = mu[..., :3], mu[..., 3:]
            values = [(g * g).sum(-1), (m * g).sum(-1)]
        else:
            values = [mu[..., 0] * mu[..., 0] + 4.0 * mu[..., 1] * mu[..., 2]]
        if _is_tensor(mu):
            import torch

            return torch.stack(values, -1)
        return np.stack(values, -1)

    # --- the PoissonSystem protocol (poisson_rs.protocols) ---------------------------------

    state_symbol: ClassVar[str] = "μ"
    #: A learned S can be trained for it (``poisson_rs.train``, the PINN on T*G).
    trainable: ClassVar[bool] = True

    def bracket_terms(self) -> BracketTerms:
        """π_ij = −Σ_k c[i,j,k] μ_k (linear)."""
        return linear_bracket_terms(self.algebra.c)

    def jet_realization(self, order: int) -> JetRealization:
        """The exact groupoid T*G ⇉ g* in the exponential chart."""
        return JetRealization(
            dim=self.dim, label="exp", exact=True, lie_constants=np.array(self.algebra.c)
        )

    def bivector(self, mu: Any) -> Any:
        """π(μ) = :meth:`poisson_tensor`: (..., n) → (..., n, n)."""
        return self.poisson_tensor(mu)

    def found_casimirs(self, max_degree: int | None = None) -> list[Polynomial]:
        """The polynomial Casimirs of its algebra up to ``max_degree`` (a null space, searched
        once per algebra; see :mod:`poisson_rs.casimirs`), for when :meth:`casimirs` knows
        no closed form."""
        from ..casimirs import DEFAULT_DEGREE, algebra_casimirs

        return algebra_casimirs(self.algebra, DEFAULT_DEGREE if max_degree is None else max_degree)

    @property
    def casimir_label(self) -> str:
        """ "C = |μ|²" (so(3)), "C = |Γ|², M·Γ" (se(3)), "C = μ_h² + 4μ_eμ_f" (sl(2)), or the
        formulas of the polynomial Casimirs the search found ("C = μ₄, μ₁² + μ₂² + μ₃²")."""
        if self.casimirs(np.ones((1, self.dim))) is not None:
            known = {"so3": "C = |μ|²", "se3": "C = |Γ|², M·Γ", "sl2": "C = μ_h² + 4μ_eμ_f"}
            return known.get(_known_algebra(self.algebra) or "", "the system's Casimirs")
        found = self.found_casimirs()
        if not found:
            return "no Casimir known (drift n/a)"
        # By formula: a count alone does not say which invariants the drift measures.
        names = self.component_names
        return "C = " + ", ".join(p.formula(names) for p in found)

    @property
    def title(self) -> str:
        """The system for titles and messages: its name and algebra."""
        name = self.name or type(self).__name__
        pretty = {"so3": "so(3)", "se3": "se(3)", "sl2": "sl(2)"}
        algebra = self.algebra.name
        if algebra in pretty:
            return f"{name} on {pretty[algebra]}*"
        return f"{name} on {algebra}*" if algebra else f"{name} on a {self.dim}-dimensional g*"

    @property
    def demo_states(self) -> FloatArray:
        """Two states for demos: on se(3)* a slow precession and a fast top with |Γ| = 1,
        else the base's two seeded states of norm 2."""
        if _known_algebra(self.algebra) == "se3":
            return np.array([[0.3, -0.8, 1.2, 0.6, 0.0, 0.8], [2.0, 0.5, -1.0, 0.0, 0.6, 0.8]])
        return super().demo_states

    def core_arrays(self) -> tuple[FloatArray, NDArray[np.int64], FloatArray]:
        """Structure constants (n, n, n) and the Hamiltonian's (powers, coeffs) as the Rust core
        takes them, computed once (the system is immutable)."""
        cached = self.__dict__.get("_core_arrays")
        if cached is None:
            powers, coeffs = self.polynomial.to_arrays()
            cached = (np.ascontiguousarray(self.algebra.c, dtype=np.float64), powers, coeffs)
            object.__setattr__(self, "_core_arrays", cached)
        return cached  # type: ignore[no-any-return]

    def step_angles(self, states: np.ndarray, h: float) -> FloatArray:
        """h × the local rate max(‖ad_∇H(μ)‖_F/√2, ‖∂f/∂μ‖_F) at each state (n, n) → (n,),
        in radians (see :attr:`poisson_rs.RolloutInfo.step_angle`)."""
        from .. import _core

        c, powers, coeffs = self.core_arrays()
        return _core.step_angles(c, powers, coeffs, states, h)  # type: ignore[no-any-return]

    def taylor_charts(self) -> tuple[str, ...]:
        """("exp",): the exponential chart of T*G exists for every algebra."""
        return ("exp",)

    def taylor_integrator(
        self, order: int, chart: str | None = None, *, tol: float, max_iter: int
    ) -> Any:
        from ..steppers.lie_poisson import lie_poisson_taylor

        chart = self.chart_or_default(chart)
        return lie_poisson_taylor(self, order, chart, tol=tol, max_iter=max_iter)

    def learn_modes(self) -> tuple[str, ...]:
        """Every mode of :func:`poisson_rs.learn`: H through Taylor-HJ on T*G, the time-h map's
        generating function, a correction to a known H."""
        return ("auto", "hamiltonian", "map", "hj+data")

    def hamiltonian_family(self, degree: int, order: int | None = None) -> Any:
        """Polynomials in μ of ``degree`` (no constant), stepped by Taylor-HJ of ``order``
        (default 7 for degree ≤ 2, else 5) in the exponential chart."""
        from ..hamiltonian_family import MonomialFamily, monomial_exponents

        algebra, n = self.algebra, self.algebra.dim
        k = order or (7 if degree <= 2 else 5)

        def build(terms: Mapping[tuple[int, ...], float]) -> LiePoissonSystem:
            return LiePoissonSystem(algebra, Polynomial(dict(terms) or {(0,) * n: 0.0}))

        return MonomialFamily(
            n,
            monomial_exponents(n, degree),
            order=k,
            chart="exp",
            build=build,
            gauge="a Casimir of the algebra",
            variables=[f"μ{i + 1}" for i in range(n)],
        )

    def classical_methods(self) -> list[str]:
        from ..steppers.lie_poisson import LIE_POISSON_METHODS

        return [m for m in LIE_POISSON_METHODS if m != "splitting"]

    def classical(self, name: str, *, tol: float, max_iter: int) -> Any:
        from ..steppers.lie_poisson import ClassicalIntegrator

        return ClassicalIntegrator(self, name, tol=tol, max_iter=max_iter)

    def reference_solution(
        self,
        x0: ArrayLike,
        times: ArrayLike,
        *,
        rtol: float = 1e-13,
        atol: float = 1e-13,
        failures: Literal["raise", "nan"] = "raise",
    ) -> FloatArray:
        from ..reference import lie_poisson_reference

        return lie_poisson_reference(self, x0, times, rtol=rtol, atol=atol, failures=failures)

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form with a "kind" key ("lie_poisson", "rigid_body" or "heavy_top")."""
        return {
            "kind": self.kind,
            "name": self.name,
            "algebra": self.algebra.to_dict(),
            "hamiltonian": self.polynomial.to_dict(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> LiePoissonSystem:
        """Rebuild any system from :meth:`to_dict`; called on a subclass, the kind must match."""
        with parsing("system dictionary"):
            return cls._from_dict(data)

    @classmethod
    def _from_dict(cls, data: Mapping[str, Any]) -> LiePoissonSystem:
        if not isinstance(data, Mapping) or "kind" not in data:
            raise ValueError("a system dictionary needs a 'kind' entry")
        kinds: dict[str, type[LiePoissonSystem]] = {
            "lie_poisson": LiePoissonSystem,
            "rigid_body": RigidBody,
            "heavy_top": HeavyTop,
        }
        kind = data["kind"]
        if kind not in kinds:
            raise ValueError(f"unknown system kind {kind!r}; expected one of {tuple(kinds)}")
        if cls is not LiePoissonSystem and kinds[kind] is not cls:
            raise ValueError(f"expected a {cls.kind!r} dictionary, got kind {kind!r}")
        try:
            if kind == "rigid_body":
                return RigidBody(data["inertia"])
            if kind == "heavy_top":
                return HeavyTop(data["inertia"], data["mgl"], data["com"])
            return LiePoissonSystem(
                LieAlgebra.from_dict(data["algebra"]),
                Polynomial.from_dict(data["hamiltonian"]),
                name=data.get("name"),
            )
        except KeyError as exc:
            raise ValueError(f"a {kind!r} dictionary needs a {exc.args[0]!r} entry") from None

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, LiePoissonSystem):
            return NotImplemented
        return (
            type(self) is type(other)
            and self.algebra == other.algebra
            and self.polynomial == other.polynomial
        )

    def __hash__(self) -> int:
        return hash((type(self).__name__, self.algebra, self.polynomial))

    def __repr__(self) -> str:
        return (
            f"LiePoissonSystem({self.algebra!r}, degree-{self.polynomial.degree} Hamiltonian with "
            f"{len(self.polynomial.terms)} terms, name={self.name!r})"
        )


def _subscript(i: int) -> str:
    """``i`` in subscript digits: 12 → "₁₂"."""
    return str(i).translate(str.maketrans("0123456789", "₀₁₂₃₄₅₆₇₈₉"))


def _known_algebra(algebra: LieAlgebra) -> str | None:
    """ "so3", "se3" or "sl2" when ``algebra`` has exactly those constants, else None."""
    for name in ("so3", "se3", "sl2"):
        if algebra == _STANDARD[name]:
            return name
    return None


_STANDARD = {"so3": LieAlgebra.so3(), "se3": LieAlgebra.se3(), "sl2": LieAlgebra.sl2()}


@dataclass(frozen=True)
class RigidBody(LiePoissonSystem):
    """Free rigid body on so(3)*: H(μ) = ½ Σ μᵢ²/Iᵢ, μ̇ = μ × (μ/I).

    Attributes
    ----------
    inertia : tuple[float, float, float]
        Principal moments of inertia (I₁, I₂, I₃), any order, all > 0; stored as a tuple of
        floats. Equality and hashing go by it.
    """

    kind: ClassVar[str] = "rigid_body"
    inertia: tuple[float, float, float] = (1.5, 2.0, 2.5)

    def __post_init__(self) -> None:
        values = _inertia(self.inertia)
        object.__setattr__(self, "inertia", values)
        weights = [1.0 / v for v in values]
        self._init_system(_STANDARD["so3"], Polynomial.quadratic_diagonal(weights), "rigid_body")

    def _inverse_inertia(self) -> FloatArray:
        return 1.0 / np.asarray(self.inertia, dtype=np.float64)

    def hamiltonian(self, mu: Any) -> Any:
        """Kinetic energy H(μ) = ½ Σ μᵢ²/Iᵢ.

        Parameters
        ----------
        mu : array_like or torch.Tensor, shape (..., 3)
            Body angular momenta.

        Returns
        -------
        ndarray or torch.Tensor, shape (...,)
        """
        m = _as_states(mu, 3)
        inv = _constant(m, self._inverse_inertia())
        return 0.5 * (m * m * inv).sum(-1)

    def casimir(self, mu: Any) -> Any:
        """Casimir C(μ) = |μ|². mu: (..., 3) → (...,)."""
        m = _as_states(mu, 3)
        return (m * m).sum(-1)

    def grad_hamiltonian(self, mu: Any) -> Any:
        """Angular velocity ∇H(μ) = μ/I (elementwise). mu: (..., 3) → (..., 3)."""
        m = _as_states(mu, 3)
        return m * _constant(m, self._inverse_inertia())

    def vector_field(self, mu: Any) -> Any:
        """Euler's equations μ̇ = μ × (μ/I). mu: (..., 3) → (..., 3)."""
        m = _as_states(mu, 3)
        if _is_tensor(m):
            import torch

            return torch.linalg.cross(m, self.grad_hamiltonian(m), dim=-1)
        return np.cross(m, m * self._inverse_inertia())

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "inertia": list(self.inertia)}

    def _directions(self) -> dict[str, FloatArray]:
        """Circulating about the smallest- and the largest-inertia axis, and within 1e-2 of the
        separatrix (on the smallest-axis side), as unit vectors."""
        i1, i2, i3 = self.inertia
        # On the unit sphere the separatrix is d₁²(I₂/I₁ − 1) = d₃²(1 − I₂/I₃) (with d₂ small).
        a, c = abs(i2 / i1 - 1.0), abs(1.0 - i2 / i3)
        out = {
            "axis 1 side": np.array([0.9, 0.3, 0.3]),
            "axis 3 side": np.array([0.3, 0.3, 0.9]),
            "separatrix": np.array([1.0, 0.05, np.sqrt(a / c) * (1.0 - 1e-2)]),
        }
        return {k: v / np.linalg.norm(v) for k, v in out.items()}

    @property
    def title(self) -> str:
        return f"free rigid body, I = {tuple(float(i) for i in self.inertia)}"

    @property
    def demo_states(self) -> FloatArray:
        """The paper's two states, (1, 1, 2) and (3, 2, 0)."""
        return np.array([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]])

    def taylor_charts(self) -> tuple[str, ...]:
        """("cayley", "exp"): the Cayley chart's closed forms exist for the rigid body only."""
        return ("cayley", "exp")

    def classical_methods(self) -> list[str]:
        from ..steppers.lie_poisson import CLASSICAL_METHODS

        return list(CLASSICAL_METHODS)

    def reference_solution(
        self,
        x0: ArrayLike,
        times: ArrayLike,
        *,
        rtol: float = 1e-13,
        atol: float = 1e-13,
        failures: Literal["raise", "nan"] = "raise",
    ) -> FloatArray:
        """DOP853 on Euler's equations written out (:func:`~poisson_rs.dop853_solution`)."""
        from ..reference import dop853_solution

        return dop853_solution(self, x0, times, rtol, atol, failures=failures)

    def reference(self, x0: np.ndarray, times: ArrayLike) -> FloatArray:
        """The closed form in Jacobi elliptic functions."""
        from ..reference import exact_solution

        return exact_solution(self, x0, times)

    reference_name: ClassVar[str] = "exact flow"


@dataclass(frozen=True)
class HeavyTop(LiePoissonSystem):
    """Heavy top on se(3)*, μ = (M, Γ) ∈ R⁶: body angular momentum M and the direction of gravity
    in the body frame Γ.

    H = ½ Σ Mᵢ²/Iᵢ + mgl χ·Γ, so Ṁ = M × Ω + mgl Γ × χ and Γ̇ = Γ × Ω with Ω = M/I. Casimirs |Γ|²
    and M·Γ.

    Attributes
    ----------
    inertia : tuple[float, float, float]
        Principal moments of inertia about the fixed point, all > 0.
    mgl : float
        Mass × gravity × distance from the fixed point to the centre of mass (energy), ≥ 0.
    com : tuple[float, float, float]
        χ, the unit-less direction of the centre of mass in the body frame (finite).
    """

    kind: ClassVar[str] = "heavy_top"
    inertia: tuple[float, float, float] = (1.0, 1.5, 2.0)
    mgl: float = 0.981
    com: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        inertia = _inertia(self.inertia)
        mgl = _real(self.mgl, "mgl")
        if mgl < 0.0:
            raise ValueError(f"mgl must be non-negative, got {mgl}")
        com = _real_triple(self.com, "com")
        if not all(math.isfinite(v) for v in com):
            raise ValueError(f"com entries must be finite, got {com}")
        object.__setattr__(self, "inertia", inertia)
        object.__setattr__(self, "mgl", mgl)
        object.__setattr__(self, "com", com)
        terms: dict[tuple[int, ...], float] = {}
        for i in range(3):
            terms[tuple(2 if j == i else 0 for j in range(6))] = 0.5 / inertia[i]
            terms[tuple(1 if j == 3 + i else 0 for j in range(6))] = mgl * com[i]
        self._init_system(_STANDARD["se3"], Polynomial(terms), "heavy_top")

    @property
    def title(self) -> str:
        return f"heavy top, I = {self.inertia}, mgl = {self.mgl:g}, χ = {self.com}"

    def classical_methods(self) -> list[str]:
        """The generic methods and the heavy top's own explicit Poisson splitting."""
        from ..steppers.lie_poisson import LIE_POISSON_METHODS

        return list(LIE_POISSON_METHODS)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "inertia": list(self.inertia),
            "mgl": self.mgl,
            "com": list(self.com),
        }


#: Standard algebras a table may name instead of giving structure constants.
NAMED_ALGEBRAS = ("so3", "se3", "sl2")

#: The keys a scene [system] table of each Lie–Poisson kind takes.
_SCENE_KEYS = {
    "rigid_body": ("kind", "inertia"),
    "heavy_top": ("kind", "inertia", "mgl", "com"),
    "lie_poisson": ("kind", "name", "algebra", "hamiltonian"),
}


def _scene_table(raw: Mapping[str, Any]) -> LiePoissonSystem:
    """A Lie–Poisson [system] table: ``kind = "rigid_body"`` (``inertia``), ``"heavy_top"``
    (``inertia``, ``mgl``, ``com``) or ``"lie_poisson"`` (``algebra``: a name of
    :data:`NAMED_ALGEBRAS` or a LieAlgebra.to_dict() table, ``hamiltonian``: a
    Polynomial.to_dict() table, optional ``name``)."""
    from functools import partial

    from ..tables import number, only_keys, required
    from ..untrusted import parsing

    kind = raw.get("kind", "lie_poisson" if "algebra" in raw else "rigid_body")
    only_keys(raw, _SCENE_KEYS[kind], kind)
    if kind == "rigid_body":
        required(raw, "inertia")
    for key in ("inertia", "com"):
        if key in raw:
            value = raw[key]
            if not isinstance(value, list) or len(value) != 3:
                raise ValueError(f"scene key 'system.{key}' must be 3 numbers, got {value!r}")
            number_ = number if key == "inertia" else partial(number, positive=False)
            raw = {**raw, key: [number_(v, f"system.{key}") for v in value]}
    if isinstance(raw.get("algebra"), str):
        name = raw["algebra"]
        if name not in NAMED_ALGEBRAS:
            raise ValueError(
                f"scene key 'system.algebra' = {name!r} is not one of {NAMED_ALGEBRAS}; give "
                "the structure constants as a table instead"
            )
        raw = {**raw, "algebra": getattr(LieAlgebra, name)().to_dict()}
    with parsing("scene", "system"):
        return LiePoissonSystem.from_dict({**raw, "kind": kind})


#: The kinds of system dictionaries and scene [system] tables this module reads.
SYSTEM_KINDS = {
    kind: LiePoissonSystem.from_dict for kind in ("lie_poisson", "rigid_body", "heavy_top")
}
SCENE_KINDS = {kind: _scene_table for kind in _SCENE_KEYS}
