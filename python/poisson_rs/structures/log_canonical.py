"""Log-canonical Poisson structures π_ij(x) = c_ij x_i x_j and their Lotka–Volterra systems.

States live in the open positive orthant x > 0. In q = ln x the bracket is the constant
antisymmetric matrix c ({q_i, q_j} = c_ij), which is why every tool below works in q and why the
structure has an exact symplectic groupoid (:mod:`poisson_rs.realizations.log_canonical`).

Hamiltonians are *log-polynomials*: H(x) = Σ_m a_m x^{e_m} − Σ_i b_i ln x_i with integer
exponent vectors e_m ≥ 0. In q every derivative of H beyond the first is a polynomial in
y = e^q, so the Hamilton–Jacobi Taylor terms are polynomials in y as well.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from fractions import Fraction
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..hamiltonian_family import MonomialFamily
from ..protocols import BracketTerms, PoissonSystemBase, provided

FloatArray = NDArray[np.float64]

#: Largest dimension the Rust core is compiled for (``poisson_rs._core.MAX_DIM``).
MAX_DIM = 10
#: Largest exponent of a Hamiltonian monomial.
MAX_EXPONENT = 16
#: Largest |c_ij|, |b_i| and |a_m|. The Taylor-HJ term S_k is a sum of products of k − 1 entries
#: of c and k coefficients of H, times factors below 16^k/k! (the exponents): with every
#: magnitude <= 1e15 the terms stay finite in float64 (< 1.8e308) through order 10, where 1e150
#: already overflows at order 3 and 1e300 at order 2.
MAX_MAGNITUDE = 1e15


def _check_magnitude(arr: FloatArray, name: str) -> None:
    """ValueError naming ``name`` and the entry when some |value| exceeds MAX_MAGNITUDE."""
    big = np.abs(arr) > MAX_MAGNITUDE
    if big.any():
        idx = tuple(int(i) for i in np.argwhere(big)[0])
        where = f"[{', '.join(map(str, idx))}]" if idx else ""
        raise ValueError(
            f"{name}{where} = {arr[idx]:.3g} exceeds {MAX_MAGNITUDE:.0e} in magnitude (the "
            "Taylor-HJ terms multiply such values and would overflow float64)"
        )


def _is_tensor(x: object) -> bool:
    return type(x).__module__.startswith("torch")


def _check_matrix(c: ArrayLike) -> FloatArray:
    """A finite antisymmetric (n, n) float64 copy of ``c``; ValueError/TypeError naming 'c'."""
    arr = np.asarray(c)
    if arr.dtype == object or arr.dtype.kind not in "fiu":
        raise TypeError(f"c must be an array of real numbers, got dtype {arr.dtype}")
    arr = np.array(arr, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[0] != arr.shape[1] or not 2 <= arr.shape[0] <= MAX_DIM:
        raise ValueError(
            f"c must be a square (n, n) matrix with 2 <= n <= {MAX_DIM} (one species has no "
            f"bracket), got shape {arr.shape}"
        )
    if not np.isfinite(arr).all():
        raise ValueError("c holds NaN or infinite values")
    _check_magnitude(arr, "c")
    if not np.array_equal(arr, -arr.T):
        i, j = np.argwhere(arr != -arr.T)[0]
        raise ValueError(
            f"c must be antisymmetric (c_ij = -c_ji): c[{i},{j}] = {arr[i, j]} but "
            f"c[{j},{i}] = {arr[j, i]}"
        )
    return arr


#: Largest |k_i| an integer Casimir vector keeps as integers: every such k is exact in float64.
INTEGER_CASIMIR_MAX = 2**53


def _exact_null_rows(c: FloatArray) -> list[list[int]]:
    """The rational null space of c as integer rows (each divided by the gcd of its entries,
    first non-zero entry positive), exact: c's entries are read as the binary fractions they
    are. Python integers, unbounded."""
    import sympy

    n = c.shape[0]
    mat = sympy.Matrix(n, n, [sympy.Rational(Fraction(float(v))) for v in c.ravel()])
    rows = []
    for v in mat.nullspace():
        den = sympy.ilcm(1, 1, *[sympy.fraction(e)[1] for e in v])  # ilcm needs two arguments
        ints = [int(e * den) for e in v]
        g = math.gcd(*ints) or 1
        first = next(k for k in ints if k != 0)
        sign = 1 if first > 0 else -1
        rows.append([sign * k // g for k in ints])
    return rows


def casimir_basis(c: FloatArray) -> NDArray[np.int64] | FloatArray:
    """The Casimir vectors of the log-canonical bracket with matrix c, (m, n) (m = 0 when c is
    invertible): the exact integer null vectors where their entries stay within
    :data:`INTEGER_CASIMIR_MAX` (monomial Casimirs Π x_i^{k_i}), int64; else the same exact
    rational vectors rounded to float64 and scaled to max |k_i| = 1 (the Casimirs Σ k_i ln x_i,
    real exponents)."""
    rows = _exact_null_rows(c)
    n = c.shape[0]
    if max((abs(k) for row in rows for k in row), default=0) <= INTEGER_CASIMIR_MAX:
        return np.array(rows, dtype=np.int64).reshape(len(rows), n)
    out = np.array(
        [[float(Fraction(k, max(abs(v) for v in row))) for k in row] for row in rows],
        dtype=np.float64,
    )
    return out.reshape(len(rows), n)


def integer_null_space(c: FloatArray) -> NDArray[np.int64]:
    """Integer vectors k spanning the rational null space of c (c k = 0), one per row, each
    divided by the gcd of its entries. The entries of c are read as the exact binary fractions
    they are, so the null space is exact. Returns an (m, n) int64 array (m = 0 when c is
    invertible); ValueError where an entry exceeds :data:`INTEGER_CASIMIR_MAX` (c with entries
    such as 0.3, whose binary fractions make the smallest integer vector astronomically long:
    :func:`casimir_basis` gives real vectors there)."""
    basis = casimir_basis(c)
    if basis.dtype != np.int64:
        big = max(abs(k) for row in _exact_null_rows(c) for k in row)
        raise ValueError(
            f"c's integer null vector has an entry of {big:.3g}, beyond 2^53: no monomial "
            "Casimir with exponents that size is meaningful (use casimir_basis)"
        )
    return basis  # type: ignore[return-value]


#: Order of accuracy and whether a step is a Poisson map, for the classical integrators of a
#: log-canonical system.
LOG_CANONICAL_METHODS: dict[str, tuple[int, bool]] = {
    "rk4": (4, False),
    "midpoint": (2, False),
    "log_splitting": (2, True),
    "log_splitting4": (4, True),
    "dop853": (8, False),
}


class LogCanonical:
    """The log-canonical Poisson structure π_ij(x) = c_ij x_i x_j on the positive orthant.

    ``c``: (n, n) antisymmetric, finite. Jacobi holds for every such c (in q = ln x the bracket
    is constant). Casimirs: Σ_i k_i ln x_i for every integer k with c k = 0.
    """

    kind = "log_canonical"

    def __init__(self, c: ArrayLike) -> None:
        self._c = _check_matrix(c)
        self._c.flags.writeable = False
        self._casimir_vectors = casimir_basis(self._c)
        self._casimir_vectors.flags.writeable = False

    @property
    def c(self) -> FloatArray:
        return self._c

    @property
    def dim(self) -> int:
        return int(self._c.shape[0])

    @property
    def casimir_vectors(self) -> NDArray[np.int64] | FloatArray:
        """(m, n) rows k with c k = 0: the Casimirs Σ k_i ln x_i, integers (monomials Π x_i^{k_i})
        where c's exact null space has integer vectors of moderate size, else real
        (:func:`casimir_basis`)."""
        return self._casimir_vectors

    def bivector(self, x: Any) -> Any:
        """π(x) = c ∘ (x xᵀ). x: (..., n) positive → (..., n, n)."""
        c: Any = self._c
        if _is_tensor(x):
            import torch

            c = torch.tensor(c, dtype=x.dtype, device=x.device)
        return c * x[..., :, None] * x[..., None, :]

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "c": self._c.tolist()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> LogCanonical:
        if not isinstance(data, Mapping) or data.get("kind") != cls.kind or "c" not in data:
            raise ValueError(f"a log-canonical structure needs kind {cls.kind!r} and 'c': {data!r}")
        return cls(data["c"])

    def __eq__(self, other: object) -> bool:
        return isinstance(other, LogCanonical) and np.array_equal(self._c, other._c)

    def __hash__(self) -> int:
        return hash(self._c.tobytes())

    def __repr__(self) -> str:
        return f"LogCanonical(c={self._c.tolist()})"


class LogPolynomial:
    """H(x) = Σ_m a_m x^{e_m} − Σ_i b_i ln x_i on the positive orthant.

    ``terms``: mapping from exponent tuples (n non-negative integers ≤ MAX_EXPONENT, not all
    zero) to finite coefficients a_m; ``b``: (n,) finite log coefficients.
    """

    def __init__(self, terms: Mapping[Any, float], b: ArrayLike) -> None:
        b_raw = np.asarray(b)
        if b_raw.dtype == object or b_raw.dtype.kind not in "fiu":
            raise TypeError(f"b must be an array of real numbers, got dtype {b_raw.dtype}")
        b_arr = np.array(b_raw, dtype=np.float64).reshape(-1)
        if not np.isfinite(b_arr).all():
            raise ValueError("b holds NaN or infinite values")
        _check_magnitude(b_arr, "b")
        n = b_arr.size
        clean: dict[tuple[int, ...], float] = {}
        for e, a in dict(terms).items():
            key = tuple(e)
            if len(key) != n or any(
                isinstance(k, bool) or not isinstance(k, numbers.Integral) for k in key
            ):
                raise ValueError(f"Hamiltonian exponent {e!r} must be {n} integers")
            if any(not 0 <= int(k) <= MAX_EXPONENT for k in key) or not any(key):
                raise ValueError(
                    f"Hamiltonian exponent {e!r} must lie in 0..={MAX_EXPONENT}, not all zero"
                )
            if isinstance(a, bool) or not isinstance(a, numbers.Real) or not math.isfinite(a):
                raise ValueError(f"Hamiltonian coefficient of {e!r} must be finite, got {a!r}")
            if abs(float(a)) > MAX_MAGNITUDE:
                raise ValueError(
                    f"Hamiltonian coefficient of {e!r} = {float(a):.3g} exceeds "
                    f"{MAX_MAGNITUDE:.0e} in magnitude (the Taylor-HJ terms would overflow)"
                )
            key = tuple(int(k) for k in key)
            clean[key] = clean.get(key, 0.0) + float(a)
        self._terms = {e: a for e, a in sorted(clean.items()) if a != 0.0}
        self._b = b_arr
        self._b.flags.writeable = False
        self._powers = np.array(list(self._terms), dtype=np.int64).reshape(-1, n)
        self._coeffs = np.array(list(self._terms.values()), dtype=np.float64)

    @property
    def dim(self) -> int:
        return int(self._b.size)

    @property
    def terms(self) -> Mapping[tuple[int, ...], float]:
        return dict(self._terms)

    @property
    def b(self) -> FloatArray:
        return self._b

    def to_arrays(self) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
        """(powers (M, n) int64, coeffs (M,), b (n,))."""
        return self._powers.copy(), self._coeffs.copy(), self._b.copy()

    def in_log(self, q: Any) -> Any:
        """H as a function of q = ln x. q: (..., n) → (...,)."""
        if _is_tensor(q):
            import torch

            p = torch.tensor(self._powers, dtype=q.dtype, device=q.device)
            a = torch.tensor(self._coeffs, dtype=q.dtype, device=q.device)
            b = torch.tensor(self._b, dtype=q.dtype, device=q.device)
            return (a * torch.exp(q @ p.T)).sum(-1) - (b * q).sum(-1)
        q = np.asarray(q, dtype=np.float64)
        return np.exp(q @ self._powers.T) @ self._coeffs - q @ self._b

    def grad_log(self, q: Any) -> Any:
        """∇_q H = Σ_m a_m e_m y^{e_m} − b. q: (..., n) → (..., n)."""
        if _is_tensor(q):
            import torch

            p = torch.tensor(self._powers, dtype=q.dtype, device=q.device)
            a = torch.tensor(self._coeffs, dtype=q.dtype, device=q.device)
            b = torch.tensor(self._b, dtype=q.dtype, device=q.device)
            return (a * torch.exp(q @ p.T)) @ p - b
        q = np.asarray(q, dtype=np.float64)
        return (np.exp(q @ self._powers.T) * self._coeffs) @ self._powers - self._b

    def to_dict(self) -> dict[str, Any]:
        return {
            "terms": [[list(e), a] for e, a in self._terms.items()],
            "b": self._b.tolist(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> LogPolynomial:
        if not isinstance(data, Mapping) or "terms" not in data or "b" not in data:
            raise ValueError(f"a log-polynomial needs 'terms' and 'b': {data!r}")
        return cls({tuple(e): a for e, a in data["terms"]}, data["b"])

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, LogPolynomial)
            and self._terms == other._terms
            and np.array_equal(self._b, other._b)
        )

    def __hash__(self) -> int:
        return hash((tuple(self._terms.items()), self._b.tobytes()))

    def __repr__(self) -> str:
        return f"LogPolynomial(terms={self._terms}, b={self._b.tolist()})"


def _positive_states(x: Any, n: int, name: str = "x") -> Any:
    """Checks the trailing dimension; ValueError for a state outside the open positive orthant
    (NaN entries pass: see below)."""
    if _is_tensor(x):
        if x.shape[-1:] != (n,):
            raise ValueError(f"{name} must have shape (..., {n}), got {tuple(x.shape)}")
        if not bool((x > 0).all()):
            raise ValueError(f"{name} must lie in the open positive orthant (every x_i > 0)")
        return x
    arr = np.asarray(x)
    if arr.dtype == object or arr.dtype.kind not in "fiu":
        raise TypeError(f"{name} must be an array of real numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if arr.ndim == 0 or arr.shape[-1] != n:
        raise ValueError(f"{name} must have shape (..., {n}), got {arr.shape}")
    # NaN passes through (H, C are NaN there): it marks the states after a failed step in a
    # trajectory, which the studies report as failures rather than refuse.
    ok = (np.isfinite(arr) & (arr > 0)) | np.isnan(arr)
    if not ok.all():
        bad = np.argwhere(~ok)[0]
        raise ValueError(
            f"{name} must lie in the open positive orthant (finite, every x_i > 0); "
            f"entry {tuple(int(i) for i in bad)} is {arr[tuple(bad)]}"
        )
    return arr


def _log(x: Any) -> Any:
    if _is_tensor(x):
        import torch

        return torch.log(x)
    return np.log(x)


class LogCanonicalSystem(PoissonSystemBase):
    """A log-canonical structure with a log-polynomial Hamiltonian: ẋ = π(x)∇H(x), i.e.
    q̇ = c ∇_q H in q = ln x. The system interface of the studies: ``dim``, ``hamiltonian``,
    ``vector_field``, ``casimirs`` (None when c is invertible), ``component_names``,
    ``to_dict``/``from_dict``.
    """

    kind = "log_canonical"

    def __init__(
        self,
        structure: LogCanonical,
        hamiltonian: LogPolynomial,
        *,
        name: str | None = None,
        component_names: Sequence[str] | None = None,
    ) -> None:
        if not isinstance(structure, LogCanonical):
            raise TypeError(f"structure must be a LogCanonical, got {type(structure).__name__}")
        if not isinstance(hamiltonian, LogPolynomial):
            raise TypeError(
                f"hamiltonian must be a LogPolynomial, got {type(hamiltonian).__name__}"
            )
        if structure.dim != hamiltonian.dim:
            raise ValueError(
                f"the structure has dimension {structure.dim}, the Hamiltonian {hamiltonian.dim}"
            )
        n = structure.dim
        names = tuple(component_names) if component_names is not None else None
        if names is None:
            sub = "₀₁₂₃₄₅₆₇₈₉"
            names = (
                ("u", "v")
                if n == 2
                else tuple("x" + "".join(sub[int(d)] for d in str(i + 1)) for i in range(n))
            )
        if len(names) != n or not all(isinstance(s, str) for s in names):
            raise ValueError(f"component_names must be {n} strings, got {component_names!r}")
        self.structure = structure
        self.log_hamiltonian = hamiltonian
        self.name = name
        self.component_names: tuple[str, ...] = names

    @property
    def dim(self) -> int:
        return self.structure.dim

    @property
    def c(self) -> FloatArray:
        return self.structure.c

    def hamiltonian(self, x: Any) -> Any:
        """H(x). x: (..., n) positive → (...,)."""
        x = _positive_states(x, self.dim)
        return self.log_hamiltonian.in_log(_log(x))

    def vector_field(self, x: Any) -> Any:
        """ẋ = π(x)∇H(x) = x ∘ (c ∇_q H(ln x)). x: (..., n) positive → (..., n)."""
        x = _positive_states(x, self.dim)
        return x * self.vector_field_log(_log(x))

    def vector_field_log(self, q: Any) -> Any:
        """q̇ = c ∇_q H(q) in q = ln x. q: (..., n) → (..., n)."""
        g = self.log_hamiltonian.grad_log(q)
        c: Any = self.c
        if _is_tensor(q):
            import torch

            c = torch.tensor(c, dtype=q.dtype, device=q.device)
        return g @ c.T

    def casimirs(self, x: Any) -> Any:
        """The monomial Casimirs in log form, Σ_i k_i ln x_i for each row k of
        ``structure.casimir_vectors``. x: (..., n) positive → (..., m), or None when c is
        invertible (no Casimir)."""
        k = self.structure.casimir_vectors
        if len(k) == 0:
            return None
        x = _positive_states(x, self.dim)
        q = _log(x)
        if _is_tensor(q):
            import torch

            return q @ torch.tensor(k.T, dtype=q.dtype, device=q.device)
        return q @ k.T.astype(np.float64)

    @property
    def casimir_degrees(self) -> tuple[int, ...]:
        """0 for each Casimir: the log forms Σ k_i ln x_i are not homogeneous, so the studies
        report their drift absolute, not relative to a power of |x₀|."""
        return (0,) * len(self.structure.casimir_vectors)

    @property
    def casimir_label(self) -> str:
        """What the Casimir drift measures, for tables and axis labels."""
        k = self.structure.casimir_vectors
        if len(k) == 0:
            return "no Casimir (c is invertible): drift n/a"
        names = self.component_names
        forms = []
        for row in k:
            parts = []
            for ki, name in zip(row.tolist(), names, strict=True):
                if ki == 0:
                    continue
                sign = "−" if ki < 0 else "+"
                mag = "" if abs(ki) == 1 else f"{abs(ki):.6g} "
                parts.append(f"{sign} {mag}ln {name}")
            text = " ".join(parts)
            forms.append(text[2:] if text.startswith("+ ") else "−" + text[2:])
        return "C = " + ", ".join(forms) + " (absolute drift)"

    # --- the PoissonSystem protocol (poisson_rs.protocols) ---------------------------------

    def bivector(self, x: Any) -> Any:
        """π(x)_ij = c_ij x_i x_j. x: (..., n) positive → (..., n, n)."""
        return self.structure.bivector(_positive_states(x, self.dim))

    def bracket_terms(self) -> BracketTerms:
        """π_ij = c_ij x_i x_j (quadratic)."""
        n, c = self.dim, self.structure.c
        terms = []
        for i in range(n):
            for j in range(i + 1, n):
                e = [0] * n
                e[i] += 1
                e[j] += 1
                terms.append((i, j, e, float(c[i, j])))
        return BracketTerms.from_terms(n, terms)

    def in_domain(self, x: np.ndarray) -> NDArray[np.bool_]:
        """(n,) bool: states in the open positive orthant (finite, every x_i > 0)."""
        arr = np.asarray(x, dtype=np.float64)
        return np.asarray((np.isfinite(arr) & (arr > 0)).all(axis=-1))

    def domain_text(self) -> str:
        return "open positive orthant (finite, every x_i > 0)"

    def sample_states(self, radii: Sequence[float]) -> tuple[FloatArray, list[str]]:
        """States x = x* ∘ exp(ρ d), all in the open positive orthant, for each fixed unit
        direction d and each log distance ρ in ``radii`` from x* = b, the equilibrium of a
        Lotka–Volterra H = Σ (x_i − b_i ln x_i) (x* = 1 when b is not positive)."""
        b = np.asarray(self.log_hamiltonian.b, dtype=np.float64)
        center = b if (b > 0).all() else np.ones_like(b)
        rows, labels = [], []
        for r in radii:
            for label, d in self._directions().items():
                rows.append(center * np.exp(r * d))
                labels.append(f"|ln x − ln x*|={r:g}, {label}")
        return np.array(rows), labels

    @property
    def demo_states(self) -> FloatArray:
        """Two states at log distance 0.5 from the equilibrium (in the positive orthant)."""
        return self.sample_states((0.5,))[0][:2]

    @property
    def title(self) -> str:
        rows = ", ".join("[" + ", ".join(f"{v:g}" for v in row) + "]" for row in self.c.tolist())
        return f"{self.name or 'Lotka–Volterra'}, log-canonical π_ij = c_ij x_i x_j, c = [{rows}]"

    #: Sizes the stability studies use: log distances |ln x − ln x*| from the equilibrium.
    sample_radii: tuple[float, ...] = (0.25, 0.5, 1.0, 1.5)

    def taylor_charts(self) -> tuple[str, ...]:
        """("log",): the exact groupoid, the step working in q = ln x."""
        return ("log",)

    def taylor_integrator(
        self, order: int, chart: str | None = None, *, tol: float, max_iter: int
    ) -> Any:
        self.chart_or_default(chart)
        return provided("log_canonical.taylor")(self, order, tol=tol, max_iter=max_iter)

    def learn_modes(self) -> tuple[str, ...]:
        """H through Taylor-HJ on the exact log-canonical groupoid (no Lie algebra for the
        other modes)."""
        return ("auto", "hamiltonian")

    def learn_degrees(self) -> tuple[int, ...]:
        """1 first: Σ a_i x_i − b_i ln x_i is Lotka–Volterra's family."""
        return (1, 2, 3)

    def hamiltonian_family(self, degree: int, order: int | None = None) -> Any:
        """H = Σ_m a_m x^{e_m} − Σ_i b_i ln x_i, the polynomial part of ``degree`` (no
        constant), stepped by Taylor-HJ of ``order`` (default 5) on the exact groupoid."""
        from ..hamiltonian_family import monomial_exponents

        structure, names, n = self.structure, self.component_names, self.dim
        k = order or 5

        def build(terms: Mapping[tuple[int, ...], float]) -> LogCanonicalSystem:
            poly = {e: c for e, c in terms.items() if min(e) >= 0}
            b = np.zeros(n)
            for e, c in terms.items():
                if min(e) < 0:
                    b[e.index(-1)] = -c
            return LogCanonicalSystem(
                structure, LogPolynomial(poly, b), name="learned", component_names=names
            )

        logs = [tuple(-int(i == j) for j in range(n)) for i in range(n)]
        return LogFamily(
            n,
            monomial_exponents(n, degree) + logs,
            order=k,
            chart="log",
            build=build,
            gauge=(
                "a Casimir of the bracket (a function of the monomials x^k with c k = 0)"
                if len(structure.casimir_vectors)
                else "nothing else (c is invertible: no Casimir)"
            ),
            variables=names,
        )

    def classical_methods(self) -> list[str]:
        return list(LOG_CANONICAL_METHODS)

    def classical(self, name: str, *, tol: float, max_iter: int) -> Any:
        return provided("log_canonical.classical")(self, name, tol=tol, max_iter=max_iter)

    def reference_solution(
        self,
        x0: ArrayLike,
        times: ArrayLike,
        *,
        rtol: float = 1e-13,
        atol: float = 1e-13,
        failures: Literal["raise", "nan"] = "raise",
    ) -> FloatArray:
        """DOP853 in q = ln x (the positive orthant is kept; the tolerances are relative in x)."""
        field_reference = provided("field_reference")
        x0 = self.check_states(x0)
        q = field_reference(
            self.vector_field_log,
            self.dim,
            np.log(x0),
            times,
            rtol=rtol,
            atol=atol,
            failures=failures,
        )
        with np.errstate(over="ignore"):
            return np.exp(q)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "name": self.name,
            "structure": self.structure.to_dict(),
            "hamiltonian": self.log_hamiltonian.to_dict(),
            "component_names": list(self.component_names),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> LogCanonicalSystem:
        if not isinstance(data, Mapping) or data.get("kind") != cls.kind:
            raise ValueError(f"expected a {cls.kind!r} system dictionary, got {data!r}")
        try:
            return cls(
                LogCanonical.from_dict(data["structure"]),
                LogPolynomial.from_dict(data["hamiltonian"]),
                name=data.get("name"),
                component_names=data.get("component_names"),
            )
        except KeyError as exc:
            raise ValueError(f"a log-canonical system needs a {exc.args[0]!r} entry") from None

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, LogCanonicalSystem)
            and self.structure == other.structure
            and self.log_hamiltonian == other.log_hamiltonian
        )

    def __hash__(self) -> int:
        return hash((self.structure, self.log_hamiltonian))

    def __reduce__(self) -> tuple[Any, ...]:
        return (_from_dict, (self.to_dict(),))

    def __repr__(self) -> str:
        label = f"name={self.name!r}, " if self.name else ""
        return f"LogCanonicalSystem({label}c={self.c.tolist()}, H={self.log_hamiltonian!r})"


def _from_dict(data: Mapping[str, Any]) -> LogCanonicalSystem:
    return LogCanonicalSystem.from_dict(data)


def lotka_volterra(c: ArrayLike, b: ArrayLike, *, name: str | None = None) -> LogCanonicalSystem:
    """The Lotka–Volterra system of the log-canonical structure c with H = Σ_i (x_i − b_i ln x_i):
    ẋ_i = x_i Σ_j c_ij (x_j − b_j).

    PNN's 2D system is ``lotka_volterra([[0, 1], [-1, 0]], [1, 2])``: u̇ = u(v − 2),
    v̇ = v(1 − u).
    """
    structure = LogCanonical(c)
    n = structure.dim
    b_raw = np.asarray(b)
    if b_raw.dtype == object or b_raw.dtype.kind not in "fiu":
        raise TypeError(f"b must be an array of real numbers, got dtype {b_raw.dtype}")
    b_arr = np.array(b_raw, dtype=np.float64).reshape(-1)
    if b_arr.size != n:
        raise ValueError(f"b must have {n} entries (one per species), got {b_arr.size}")
    terms = {tuple(int(i == j) for j in range(n)): 1.0 for i in range(n)}
    return LogCanonicalSystem(structure, LogPolynomial(terms, b_arr), name=name)


def _scene_table(raw: Mapping[str, Any]) -> LogCanonicalSystem:
    """A ``kind = "lotka_volterra"`` [system] table: the log-canonical structure ``c`` (n × n,
    antisymmetric) with H = Σ (x_i − b_i ln x_i) (``b``: n numbers), optional ``name``."""
    from ..tables import matrix, number, only_keys, optional_name, required
    from ..untrusted import parsing

    only_keys(raw, ("kind", "c", "b", "name"), "lotka_volterra")
    required(raw, "c", "b")
    c = matrix(raw["c"], "system.c")
    b = raw["b"]
    if not isinstance(b, list) or len(b) != len(c):
        raise ValueError(f"scene key 'system.b' must be {len(c)} numbers (one per species)")
    b_values = [number(v, "system.b", positive=False) for v in b]
    name = optional_name(raw)
    with parsing("scene", "system.c"):
        return lotka_volterra(c, b_values, name=name)


#: The kinds of system dictionaries (``to_dict()``) and of scene [system] tables this module
#: reads (found by :func:`poisson_rs.structures.system_from_dict` and the scenes).
SYSTEM_KINDS = {LogCanonicalSystem.kind: LogCanonicalSystem.from_dict}
SCENE_KINDS = {"lotka_volterra": _scene_table}


class LogFamily(MonomialFamily):
    """The Hamiltonians of :meth:`LogCanonicalSystem.hamiltonian_family`: monomials x^e, and
    ln x_i written as the exponent −e_i (its key; not a power)."""

    @property
    def degree(self) -> int:
        return max((sum(e) for e in self.exponents if min(e) >= 0), default=0)

    @property
    def name(self) -> str:
        return f"log+poly{self.degree}"

    @property
    def description(self) -> str:
        return (
            f"Σ_i θ_i ln x_i plus a polynomial in ({', '.join(self.variables)}) of degree ≤ "
            f"{self.degree} without constant term ({len(self.exponents)} terms)"
        )

    def gradients(self, x: Any) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        logs = [m for m, e in enumerate(self.exponents) if min(e) < 0]
        mono = [m for m in range(len(self.exponents)) if m not in logs]
        out = np.zeros((len(x), self.dim, len(self.exponents)))
        if mono:
            part = self.restrict([self.exponents[m] for m in mono])
            out[:, :, mono] = MonomialFamily.gradients(part, x)
        for m in logs:
            i = self.exponents[m].index(-1)
            out[:, i, m] = 1.0 / x[:, i]
        return out

    def text(self, theta: Any) -> str:
        parts = []
        for e, c in self.terms(theta).items():
            if min(e) < 0:
                parts.append(f"{float(c)!r}*ln({self.variables[e.index(-1)]})")
            else:
                pairs = zip(self.variables, e, strict=True)
                factors = [f"{v}**{k}" if k > 1 else v for v, k in pairs if k]
                parts.append("*".join([repr(float(c)), *factors]))
        return " + ".join(parts) or "0"


def _log_canonical_brackets(dim: int) -> Any:
    """π_ij = c_ij x_i x_j with c constant and antisymmetric (θ = c_ij, i < j): every θ obeys
    Jacobi; only states in the positive orthant."""
    from ..bracket_family import BracketFamily

    if dim < 2:
        return None
    pairs = [(i, j) for i in range(dim) for j in range(i + 1, dim)]

    def build(theta: NDArray[np.float64]) -> LogCanonicalSystem:
        c = np.zeros((dim, dim))
        for (i, j), t in zip(pairs, theta, strict=True):
            c[i, j], c[j, i] = t, -t
        return LogCanonicalSystem(LogCanonical(c), LogPolynomial({}, np.zeros(dim)), name="learned")

    def domain(states: NDArray[np.float64]) -> str | None:
        return None if bool(np.all(states > 0)) else "a state is not in the positive orthant"

    return BracketFamily(
        "log-canonical",
        dim,
        [(i, j, tuple(int(k in (i, j)) for k in range(dim))) for i, j in pairs],
        build=build,
        description="π_ij = c_ij x_i x_j, c constant (Jacobi holds for every c)",
        jacobi_free=True,
        domain=domain,
        template=np.ones(len(pairs)),
    )


BRACKET_FAMILIES = {"log-canonical": _log_canonical_brackets}
