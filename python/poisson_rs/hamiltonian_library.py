"""A term library of Hamiltonians beyond polynomials, H_θ = Σ_m θ_m φ_m with φ_m monomials of
degree ≤ d and sin x_i, cos x_i of each coordinate, or monomials of degree ≤ d and functions of
linear forms (exp(±x_i) and exp(x_i − x_j): a Toda lattice, Lotka–Volterra in log coordinates;
sin and cos of x_i − x_j: coupled pendula, Josephson-junction chains), or monomials of degree ≤ d
and the log-distances ln|z_a − z_b|² of planar points, or monomials of degree ≤ d and powers of
distances |z_a − z_b|^p, |z_a|^p (p < 0: the Coulomb and Kepler potentials), or monomials of
degree ≤ d, sin x_i, cos x_i and the products x_j sin x_i, x_j cos x_i (a pendulum whose gravity
term a second coordinate scales: a pendulum on a spring, a driven support), on any structure that
steps expression Hamiltonians by jets
(:meth:`poisson_rs.protocols.PoissonSystemBase.jet_realization`).

Linear forms: the dictionary is the coordinates and their pairwise differences with coefficients
±1 (every ordered pair for exp, whose sign matters; one order for sin and cos, whose sign only
flips a coefficient), and the harmonics 2x_i and 3x_i of each coordinate for sin and cos (the
torsion potentials Σ_n k_n cos(nφ − δ_n) of molecular dihedral angles, a rotor in a quadrupole
field). Other frequencies are not searched: a term is linear in θ only where its form is fixed.

Planar points: where the dimension n is even, the coordinates are read as n/2 consecutive pairs,
z_a = (x_{2a+1}, x_{2a+2}) for a = 0 … n/2 − 1 (0-based a, 1-based coordinates as in x1 … xn), and
the log-distance terms are ln((x_{2a+1} − x_{2b+1})² + (x_{2a+2} − x_{2b+2})²) for each pair a < b.
That is the only pairing tried (it is a rule on positions, not a guess at the system); where n is
odd or below 4 there are no such terms and a family asking for them is refused.

Powers of distances use the same points: |z_a − z_b|^p for each pair a < b and |z_a|^p, the
distance of each point from the origin, for each power p of ``distance_powers`` (among
:data:`DISTANCE_POWERS`; ``pr.learn`` tries p = −1 only). In canonical coordinates ordered
(q1, q2, p1, p2) the points are z_0 = q and z_1 = p, so planar Kepler's −1/|q| is ``("radius", −1,
0)``; the terms that pair a position with a momentum (|q − p|^p, |p|^p) mean nothing there and
are fitted to near zero (on exact records they absorb a little of the integrator's truncation
error, as every spare term does). For N planar bodies, order the coordinates (q_1x, q_1y, …,
q_Nx, q_Ny, then the momenta) so that the first N points are the bodies.

It offers what :func:`poisson_rs.learn.structure_fit.fit_structure_hamiltonian` asks of a
family (as :class:`poisson_rs.hamiltonian_family.MonomialFamily` does): the gradients of the φ_m
(so the vector field is linear in θ), the structure's integrator of H_θ (here Taylor-HJ by jets
of H_θ written as an expression: built in about a millisecond), the learned system, and a text.
A term is named by its key: an exponent tuple for a monomial, ``("sin", i)`` or ``("cos", i)``
for the trigonometric ones (i the 0-based coordinate), ``("xsin", j, i)`` and ``("xcos", j, i)``
for x_j sin x_i and x_j cos x_i, ``("logdist", a, b)`` for ln|z_a − z_b|²
(a < b, 0-based points), ``("dist", p, a, b)`` for |z_a − z_b|^p, ``("radius", p, a)`` for
|z_a|^p, and ``(f, form)`` for f(ℓ·x) with f among exp, sin, cos and ``form`` the tuple of the n
integer coefficients of ℓ (``("exp", (1, -1, 0, 0))`` is exp(x1 − x2)). Nothing here names a
structure.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .hamiltonian_family import monomial_exponents
from .protocols import NEWTON_MAX_ITER, NEWTON_TOL

__all__ = [
    "DISTANCE_POWERS",
    "EXP_ARGUMENT_MAX",
    "HARMONICS",
    "LIBRARY_DEGREES",
    "LIBRARY_DISTANCE_DEGREES",
    "LIBRARY_DISTANCE_POWERS",
    "LIBRARY_FORM_DEGREES",
    "LIBRARY_ORDER",
    "LibraryFamily",
    "check_distance_powers",
    "distance_pairs",
    "library_families",
    "linear_forms",
    "structure_gauge",
    "supports_library",
]

FloatArray = NDArray[np.float64]
# tuple[int, ...] | tuple[str, int] | tuple[str, int, int] | tuple[str, int, int, int]
Key = Any

#: Taylor-HJ order (by jets) of the library's integrator: order 3 costs ~0.3 ms a step on a
#: 3-D affine bracket, order 5 ~3.5 ms (docs/hamiltonians.md).
LIBRARY_ORDER = 5
#: Polynomial degrees of the library tried by ``pr.learn``, after the polynomial families.
LIBRARY_DEGREES = (2, 3)
#: Polynomial degrees of the log-distance library tried by ``pr.learn``, after the trigonometric
#: ones and only where the dimension is even and ≥ 4: degree 2 also covers a uniform or linear
#: background flow (the linear and angular impulses are of degree ≤ 2).
LIBRARY_DISTANCE_DEGREES = (2,)
#: Polynomial degrees of the linear-form libraries tried by ``pr.learn`` (poly+exp, then
#: poly+trig+trigdiff, then poly+trig+xtrig), after poly+trig: degree 2 holds the kinetic energy
#: of a canonical system.
LIBRARY_FORM_DEGREES = (2,)
#: Powers of distances a library may hold: the inverse-distance (Kepler, Coulomb, −1),
#: inverse-square (−2: a centrifugal barrier) and inverse-cube (−3: a dipole) laws. Positive even
#: powers are polynomials already.
DISTANCE_POWERS = (-1, -2, -3)
#: Powers of distances tried by ``pr.learn`` (with the degrees of :data:`LIBRARY_DISTANCE_DEGREES`,
#: after the log-distances): −1 alone, since each power adds k(k + 1)/2 terms for k points.
LIBRARY_DISTANCE_POWERS = (-1,)
#: Two points closer than this, relative to 1 + |z_a| + |z_b|, count as coinciding: ln|z_a − z_b|²
#: and its gradient ~1/|z_a − z_b| are then no longer representable to any useful accuracy.
COINCIDE_RTOL = 1e-12
#: The multiples n·x_i whose sine and cosine the harmonics library holds (n = 1 is "trig").
HARMONICS = (2, 3)
#: Largest argument of an exponential term on the records: e^x overflows float64 past ~709.8,
#: and its gradient with it.
EXP_ARGUMENT_MAX = 700.0


def supports_library(structure: Any) -> bool:
    """Whether ``structure`` steps expression Hamiltonians by jets (an exact or order-n jet
    realization)."""
    return bool(structure.steps_expressions_by_jets())


def distance_pairs(dim: int) -> list[tuple[int, int]]:
    """The pairs (a, b), a < b, of planar points z_a = (x_{2a+1}, x_{2a+2}) of an even ``dim``
    ≥ 4 (0-based point indices). ValueError for an odd ``dim`` or one below 4."""
    if dim % 2 or dim < 4:
        raise ValueError(
            "distance terms read the coordinates as planar points (x1, x2), (x3, x4), …: "
            f"the dimension must be even and at least 4, got {dim}"
        )
    k = dim // 2
    return [(a, b) for a in range(k) for b in range(a + 1, k)]


def linear_forms(dim: int, kind: str) -> list[tuple[int, ...]]:
    """The forms ℓ (tuples of ``dim`` integer coefficients) of the library's ``kind`` of terms:
    "exp": ±x_i for each coordinate and x_i − x_j for each ordered pair i ≠ j; "trigdiff":
    x_i − x_j for i < j (sin and cos of the coordinates themselves are the "trig" terms);
    "harmonics": n·x_i for each coordinate and each n of :data:`HARMONICS`."""

    def form(pos: int, neg: int | None = None, sign: int = 1) -> tuple[int, ...]:
        out = [0] * dim
        out[pos] = sign
        if neg is not None:
            out[neg] = -1
        return tuple(out)

    pairs = [(i, j) for i in range(dim) for j in range(i + 1, dim)]
    if kind == "harmonics":
        return [form(i, sign=n) for i in range(dim) for n in HARMONICS]
    if kind == "trigdiff":
        return [form(i, j) for i, j in pairs]
    if kind == "exp":
        singles = [form(i, sign=s) for i in range(dim) for s in (1, -1)]
        return singles + [form(i, j) for i, j in pairs] + [form(j, i) for i, j in pairs]
    raise ValueError(f"kind must be 'exp', 'trigdiff' or 'harmonics', got {kind!r}")


def _form_text(variables: Sequence[str], form: Sequence[int]) -> str:
    """ℓ·x as text: ``x1 - x2``, ``-x1``, ``2*x3``."""
    parts = []
    for v, c in zip(variables, form, strict=True):
        if c == 0:
            continue
        mag = v if abs(c) == 1 else f"{abs(c)}*{v}"
        parts.append(("- " if c < 0 else "+ ") + mag)
    text = " ".join(parts)
    return "-" + text[2:] if text.startswith("- ") else text[2:]


def check_distance_powers(powers: Any) -> tuple[int, ...]:
    """``powers`` as a tuple of distinct integers among :data:`DISTANCE_POWERS`; ValueError
    naming ``distance_powers`` otherwise."""
    try:
        items = list(powers)
    except TypeError:
        items = None
    if (
        items is None
        or isinstance(powers, str)
        or any(isinstance(p, bool) or not isinstance(p, (int, np.integer)) for p in items)
        or any(int(p) not in DISTANCE_POWERS for p in items)
        or len(set(map(int, items))) != len(items)
    ):
        raise ValueError(
            f"distance_powers must be distinct integers among {DISTANCE_POWERS} (the exponent "
            f"p of |z_a − z_b|^p and |z_a|^p), got {powers!r}"
        )
    return tuple(int(p) for p in items)


def library_families(structure: Any, order: int | None, top: int) -> list[LibraryFamily]:
    """The term libraries ``pr.learn`` tries on ``structure`` after its polynomials, smallest
    first: poly+trig of :data:`LIBRARY_DEGREES`, then, where the dimension is even and ≥ 4,
    poly+logdist of :data:`LIBRARY_DISTANCE_DEGREES`, then poly+dist^p of the same degrees and the
    powers :data:`LIBRARY_DISTANCE_POWERS` (k(k + 1)/2 terms a power for k points, more than the
    k(k − 1)/2 log-distances: data those explain never pay for them), then the linear forms of
    :data:`LIBRARY_FORM_DEGREES`: poly+exp, (dimension ≥ 2) poly+trig+trigdiff, then the products
    of coordinates with sines and cosines, poly+trig+xtrig (2n² more terms), and the harmonics
    sin, cos of 2x_i and 3x_i, poly+trig+harmonics. Degrees above
    ``top`` are left out, and libraries whose H_θ exceeds the expression limits; none where the
    structure does not step expressions by jets."""
    if not supports_library(structure):
        return []
    out = [LibraryFamily(structure, d, order) for d in LIBRARY_DEGREES if d <= top]
    dim = int(structure.dim)
    if dim % 2 == 0 and dim >= 4:
        out += [
            LibraryFamily(structure, d, order, trig=False, log_distances=True)
            for d in LIBRARY_DISTANCE_DEGREES
            if d <= top
        ]
        out += [
            LibraryFamily(structure, d, order, trig=False, distance_powers=LIBRARY_DISTANCE_POWERS)
            for d in LIBRARY_DISTANCE_DEGREES
            if d <= top
        ]
    # Functions of linear forms last: 2n + n(n − 1) exponentials and n(n − 1) sines and cosines
    # of differences, more terms than any library above for n ≥ 3.
    out += [
        LibraryFamily(structure, d, order, trig=False, exponentials=True)
        for d in LIBRARY_FORM_DEGREES
        if d <= top
    ]
    if dim >= 2:  # in 1-D there are no differences: poly+trig again
        out += [
            LibraryFamily(structure, d, order, differences=True)
            for d in LIBRARY_FORM_DEGREES
            if d <= top
        ]
    out += [
        LibraryFamily(structure, d, order, products=True) for d in LIBRARY_FORM_DEGREES if d <= top
    ]
    out += [
        LibraryFamily(structure, d, order, harmonics=True) for d in LIBRARY_FORM_DEGREES if d <= top
    ]
    # H_θ with every term must be one expression (its integrator steps that text): in high
    # dimensions the larger libraries exceed the expression limits and could never be fitted.
    return [f for f in out if f.writable()]


def _number(c: float) -> str:
    return f"({float(c)!r})"


def _squared(v: Sequence[str], a: int, b: int | None) -> str:
    """|z_a − z_b|² (|z_a|² where ``b`` is None) as text in the component names ``v``."""
    i = 2 * a
    if b is None:
        return f"{v[i]}**2 + {v[i + 1]}**2"
    j = 2 * b
    return f"({v[i]} - {v[j]})**2 + ({v[i + 1]} - {v[j + 1]})**2"


def structure_gauge(structure: Any) -> str:
    """What H is identifiable up to on ``structure``, as its own polynomial family says (the
    same bracket, so the same Casimirs); the generic phrase where it offers none."""
    offer = getattr(structure, "hamiltonian_family", None)
    degrees = getattr(structure, "learn_degrees", None)
    if offer is None or degrees is None:
        return "a Casimir of the bracket"
    try:
        return str(offer(min(degrees()), None).gauge)
    except (NotImplementedError, ValueError):  # the structure offers no polynomial family
        return "a Casimir of the bracket"


class LibraryFamily:
    """H_θ over monomials of degree ≤ ``degree`` (no constant), sin and cos of each coordinate
    (``trig``), exp(±x_i) and exp(x_i − x_j) (``exponentials``), sin and cos of x_i − x_j
    (``differences``; see :func:`linear_forms`), x_j sin x_i and x_j cos x_i for every j and i
    (``products``), sin and cos of n·x_i for n in :data:`HARMONICS` (``harmonics``), the
    log-distances ln|z_a − z_b|² of planar
    points (``log_distances``) and the powers |z_a − z_b|^p, |z_a|^p for each p of
    ``distance_powers`` (among :data:`DISTANCE_POWERS`; see the module docstring: both distance
    options raise ValueError where the dimension is odd or below 4), on the bracket of
    ``structure``, stepped by Taylor-HJ by jets of ``order``. Distances are in the units of the
    coordinates.

    ``keys`` restricts the family to those terms (see :meth:`restrict`); ``gauge`` is what H is
    identifiable up to, as text (default: what the structure's own polynomial family says).
    """

    def __init__(
        self,
        structure: Any,
        degree: int,
        order: int | None = None,
        *,
        keys: Sequence[Key] | None = None,
        trig: bool = True,
        log_distances: bool = False,
        distance_powers: Sequence[int] = (),
        exponentials: bool = False,
        differences: bool = False,
        products: bool = False,
        harmonics: bool = False,
        gauge: str | None = None,
    ) -> None:
        self.structure = structure
        self.dim = int(structure.dim)
        self.variables = tuple(str(v) for v in structure.component_names)
        self.order = order or LIBRARY_ORDER
        self.chart = "jets"
        self._degree = degree
        self.trig, self.log_distances = bool(trig), bool(log_distances)
        self.distance_powers = check_distance_powers(distance_powers)
        self.exponentials, self.differences = bool(exponentials), bool(differences)
        self.products, self.harmonics = bool(products), bool(harmonics)
        every: list[Key] = list(monomial_exponents(self.dim, degree))
        if self.trig:
            every += [(f, i) for i in range(self.dim) for f in ("sin", "cos")]
        if self.exponentials:
            every += [("exp", ell) for ell in linear_forms(self.dim, "exp")]
        if self.differences:
            diffs = linear_forms(self.dim, "trigdiff")
            every += [(f, ell) for ell in diffs for f in ("sin", "cos")]
        if self.products:
            n = self.dim
            every += [(f, j, i) for j in range(n) for i in range(n) for f in ("xsin", "xcos")]
        if self.harmonics:
            multiples = linear_forms(self.dim, "harmonics")
            every += [(f, ell) for ell in multiples for f in ("sin", "cos")]
        if self.log_distances:
            every += [("logdist", a, b) for a, b in distance_pairs(self.dim)]
        for p in self.distance_powers:
            every += [("dist", p, a, b) for a, b in distance_pairs(self.dim)]
            every += [("radius", p, a) for a in range(self.dim // 2)]
        self.exponents: list[Key] = every if keys is None else [self._key(k) for k in keys]
        if not self.exponents or any(k not in every for k in self.exponents):
            raise ValueError(f"keys must be terms of the library {self.name}")
        # Asking the structure builds its polynomial family: done once, then handed on by
        # ``restrict`` (called per refit).
        self.gauge = structure_gauge(structure) if gauge is None else gauge

    @staticmethod
    def _key(k: Any) -> Key:
        key = tuple(k)
        # A linear form given as a list (a key read back from JSON) compares as its tuple.
        if len(key) == 2 and isinstance(key[0], str) and isinstance(key[1], (list, tuple)):
            key = (key[0], tuple(key[1]))
        return key

    def __len__(self) -> int:
        return len(self.exponents)

    @property
    def degree(self) -> int:
        return self._degree

    @property
    def name(self) -> str:
        return (
            f"poly{self._degree}"
            + ("+trig" if self.trig else "")
            + ("+exp" if self.exponentials else "")
            + ("+trigdiff" if self.differences else "")
            + ("+xtrig" if self.products else "")
            + ("+harmonics" if self.harmonics else "")
            + ("+logdist" if self.log_distances else "")
            + "".join(f"+dist^{p}" for p in self.distance_powers)
        )

    @property
    def description(self) -> str:
        extra = []
        if self.trig:
            extra.append("sin and cos of each coordinate")
        if self.exponentials:
            extra.append("exp(±x_i) and exp(x_i − x_j) of the coordinates")
        if self.differences:
            extra.append("sin and cos of x_i − x_j")
        if self.products:
            extra.append("x_j sin x_i and x_j cos x_i")
        if self.harmonics:
            extra.append("sin and cos of " + " and ".join(f"{n}x_i" for n in HARMONICS))
        # Planar points exist only in even dimensions (the distance options refuse the others).
        points = ", ".join(
            f"({a}, {b})" for a, b in zip(self.variables[::2], self.variables[1::2], strict=False)
        )
        if self.log_distances:
            extra.append(f"ln|z_a − z_b|² of the points {points}")
        for p in self.distance_powers:
            extra.append(f"|z_a − z_b|^{p} and |z_a|^{p} of the points {points}")
        return (
            f"a polynomial in ({', '.join(self.variables)}) of degree ≤ {self._degree} without "
            f"constant term plus {' and '.join(extra)} ({len(self)} terms)"
        )

    def restrict(self, keys: Sequence[Key]) -> LibraryFamily:
        """The same library on fewer terms."""
        return LibraryFamily(
            self.structure,
            self._degree,
            self.order,
            keys=list(keys),
            trig=self.trig,
            log_distances=self.log_distances,
            distance_powers=self.distance_powers,
            exponentials=self.exponentials,
            differences=self.differences,
            products=self.products,
            harmonics=self.harmonics,
            gauge=self.gauge,
        )

    def writable(self) -> bool:
        """Whether H_θ with every term fits the expression limits
        (:data:`poisson_rs.expressions.MAX_INSTRUCTIONS`), as its integrator needs."""
        from .expressions import Expression, ExpressionError

        try:
            # Distinct coefficients: equal ones would share one constant instruction.
            Expression(self.text(1.0 + np.arange(len(self))), self.variables)
        except ExpressionError:
            return False
        return True

    def _pairs(self) -> list[tuple[int, int]]:
        pairs = [(k[1], k[2]) for k in self.exponents if k[0] == "logdist"]
        pairs += [(k[2], k[3]) for k in self.exponents if k[0] == "dist"]
        return sorted(set(pairs))

    def _centred(self) -> list[int]:
        return sorted({k[2] for k in self.exponents if k[0] == "radius"})

    def check_states(self, x: Any, name: str = "trajectories") -> None:
        """ValueError naming ``name`` where a state of ``x`` (B, n) has two points of a
        log-distance or distance-power term at the same place, or the point of a |z_a|^p term at
        the origin (within :data:`COINCIDE_RTOL`): those terms are singular there; or where an
        exponential term's argument ℓ·x exceeds :data:`EXP_ARGUMENT_MAX` (e^{ℓ·x} and its
        gradient overflow or swamp every other term). Nothing to check for the other terms,
        defined and bounded everywhere."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, self.dim)
        forms = [k[1] for k in self.exponents if k[0] == "exp"]
        if forms:
            args = x @ np.asarray(forms, dtype=np.float64).T
            worst = np.unravel_index(int(np.argmax(args)), args.shape)
            if args[worst] > EXP_ARGUMENT_MAX:
                k, m = int(worst[0]), int(worst[1])
                term = _form_text(self.variables, forms[m])
                raise ValueError(
                    f"{name}: {int((args > EXP_ARGUMENT_MAX).any(axis=1).sum())} record(s) give "
                    f"the term library {self.name}'s exp({term}) an argument above "
                    f"{EXP_ARGUMENT_MAX:g}, e.g. {args[worst]:.6g} in the state {x[k].tolist()}: "
                    "it overflows there"
                )
        for a in self._centred():
            za = x[:, 2 * a : 2 * a + 2]
            r = np.linalg.norm(za, axis=1)
            bad = r <= COINCIDE_RTOL * (1.0 + r)
            if bad.any():
                k = int(np.argmax(bad))
                va = self.variables[2 * a : 2 * a + 2]
                raise ValueError(
                    f"{name}: {int(bad.sum())} record(s) put point {a + 1} at the origin, e.g. "
                    f"({', '.join(va)}) = ({za[k, 0]:.6g}, {za[k, 1]:.6g}) in the state "
                    f"{x[k].tolist()}: the term library {self.name}'s |z_{a + 1}|^p is singular "
                    "there"
                )
        for a, b in self._pairs():
            za, zb = x[:, 2 * a : 2 * a + 2], x[:, 2 * b : 2 * b + 2]
            gap = np.linalg.norm(za - zb, axis=1)
            bad = gap <= COINCIDE_RTOL * (
                1.0 + np.linalg.norm(za, axis=1) + np.linalg.norm(zb, axis=1)
            )
            if bad.any():
                k = int(np.argmax(bad))
                va, vb = self.variables[2 * a : 2 * a + 2], self.variables[2 * b : 2 * b + 2]
                raise ValueError(
                    f"{name}: {int(bad.sum())} record(s) put points {a + 1} and {b + 1} at the "
                    f"same place, e.g. ({', '.join(va)}) = ({', '.join(vb)}) = "
                    f"({za[k, 0]:.6g}, {za[k, 1]:.6g}) in the state {x[k].tolist()}: the term "
                    f"library {self.name}'s terms in |z_{a + 1} − z_{b + 1}| are singular there"
                )

    def gradients(self, x: Any) -> FloatArray:
        """∇φ_m at states (B, n) → (B, n, P)."""
        x = np.asarray(x, dtype=np.float64)
        out = np.zeros((len(x), self.dim, len(self)))
        for m, key in enumerate(self.exponents):
            if key[0] == "logdist":
                # ∇ ln r² = 2 (z_a − z_b)/r² on z_a, the opposite on z_b.
                _, a, b = key
                d = x[:, 2 * a : 2 * a + 2] - x[:, 2 * b : 2 * b + 2]
                g = 2.0 * d / np.sum(d * d, axis=1, keepdims=True)
                out[:, 2 * a : 2 * a + 2, m] = g
                out[:, 2 * b : 2 * b + 2, m] = -g
                continue
            if key[0] in ("dist", "radius"):
                # ∇ r^p = p r^(p−2) d, d = z_a − z_b (or z_a), on z_a; the opposite on z_b.
                p, a = key[1], key[2]
                d = x[:, 2 * a : 2 * a + 2].copy()
                if key[0] == "dist":
                    d -= x[:, 2 * key[3] : 2 * key[3] + 2]
                r2 = np.sum(d * d, axis=1, keepdims=True)
                g = p * r2 ** ((p - 2) / 2) * d
                out[:, 2 * a : 2 * a + 2, m] = g
                if key[0] == "dist":
                    out[:, 2 * key[3] : 2 * key[3] + 2, m] = -g
                continue
            if key[0] in ("xsin", "xcos"):
                # ∇ x_j s(x_i) = s(x_i) e_j + x_j s'(x_i) e_i (both on x_i where j = i).
                _, j, i = key
                sin, cos = np.sin(x[:, i]), np.cos(x[:, i])
                out[:, j, m] += sin if key[0] == "xsin" else cos
                out[:, i, m] += x[:, j] * (cos if key[0] == "xsin" else -sin)
                continue
            if isinstance(key[0], str) and isinstance(key[1], tuple):
                # ∇ f(ℓ·x) = f'(ℓ·x) ℓ.
                f, ell = key
                arg = x @ np.asarray(ell, dtype=np.float64)
                slope = np.exp(arg) if f == "exp" else np.cos(arg) if f == "sin" else -np.sin(arg)
                out[:, :, m] = slope[:, None] * np.asarray(ell, dtype=np.float64)
                continue
            if isinstance(key[0], str):
                f, i = key
                out[:, i, m] = np.cos(x[:, i]) if f == "sin" else -np.sin(x[:, i])
                continue
            e = np.array(key, dtype=np.int64)
            for i in range(self.dim):
                if e[i] == 0:
                    continue
                lowered = e.copy()
                lowered[i] -= 1
                out[:, i, m] = e[i] * np.prod(x**lowered, axis=1)
        return out

    def terms(self, theta: Any) -> dict[Key, float]:
        """θ as {key: coefficient}, zeros dropped."""
        return {k: float(t) for k, t in zip(self.exponents, theta, strict=True) if t != 0.0}

    def _term_text(self, key: Key) -> str:
        if key[0] == "logdist":
            v, a, b = self.variables, 2 * key[1], 2 * key[2]
            return f"log(({v[a]} - {v[b]})**2 + ({v[a + 1]} - {v[b + 1]})**2)"
        if key[0] in ("dist", "radius"):
            # r^p = (r²)^(p/2): an integer or half-integer power, one tape instruction (powi or
            # powf), which the jets differentiate exactly.
            b = key[3] if key[0] == "dist" else None
            return f"({_squared(self.variables, key[2], b)})**({key[1] / 2!r})"
        if key[0] in ("xsin", "xcos"):
            return f"{self.variables[key[1]]}*{key[0][1:]}({self.variables[key[2]]})"
        if isinstance(key[0], str) and isinstance(key[1], tuple):
            return f"{key[0]}({_form_text(self.variables, key[1])})"
        if isinstance(key[0], str):
            return f"{key[0]}({self.variables[key[1]]})"
        return "*".join(
            f"{v}**{p}" if p > 1 else v for v, p in zip(self.variables, key, strict=True) if p
        )

    def text(self, theta: Any) -> str:
        """H_θ as an expression in the component names (floats by repr, which round-trips)."""
        parts = [f"{_number(c)}*{self._term_text(k)}" for k, c in self.terms(theta).items()]
        return " + ".join(parts) or "0"

    def system(self, theta: Any) -> Any:
        """The structure's bracket with H = H_θ (its expression system)."""
        from .structures.expression_system import with_hamiltonian

        return with_hamiltonian(self.structure, self.text(theta), name="learned")

    def stepper(self, theta: Any, system: Any = None) -> Any:
        """Taylor-HJ by jets of :attr:`order` for H_θ."""
        built = system if system is not None else self.system(theta)
        return built.taylor_integrator(self.order, tol=NEWTON_TOL, max_iter=NEWTON_MAX_ITER)
