"""The algebra under every Lie–Poisson structure: a Lie algebra by its structure constants
(:class:`LieAlgebra`) and polynomials on g* ≅ Rⁿ (:class:`Polynomial`), with the helpers they
share. It imports no system, so that :mod:`poisson_rs.casimirs` (Casimirs of an algebra) sits
between it and the systems of :mod:`.lie_poisson` that use them.

Every class evaluates on NumPy arrays and, differentiably, on torch tensors; torch is imported only
when a tensor arrives.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..protocols import BracketTerms
from ..untrusted import parsing

__all__ = ["LieAlgebra", "Polynomial"]

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

        # A copy: the constants are read-only arrays (and torch.compile traces from_numpy
        # without the warning it gives torch.tensor of an array it has turned into a tensor).
        return torch.from_numpy(np.array(values)).to(dtype=xp_like.dtype, device=xp_like.device)
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
