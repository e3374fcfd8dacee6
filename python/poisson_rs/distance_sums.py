"""Hamiltonians that are sums over distances, recognised in an expression's program.

H(x) = Σ_k w_k φ_k(r_k²) + P(x), r_k² = Σ_{d<D} (x_{a_kd} − x_{b_kd})² (D ≤ 3; or Σ x_{a_kd}², the
distance from the origin), φ = ln or a power of r² (r⁻¹, r, r⁻², …), P a polynomial: point
vortices, Kepler, gravitating and charged bodies.
The core evaluates such an H's gradient as compiled code term by term (``rust/distance_sum.rs``),
about 3× its interpreted field program; every other H keeps the program. Recognition reads the
program H was parsed into, so it takes the forms that grammar writes: ``log((x1 - x3)**2 + (x2 -
x4)**2)``, ``1/sqrt(...)``, ``(...)**-1.5``, ``log(sqrt(...))``, scaled and summed. Constant
terms are dropped (the table serves ∇H only: H itself is the program's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .expressions import Node

#: The most coordinates of a point (the core's ``MAX_POINT_DIM``).
MAX_POINT_DIM = 3
#: The most distance terms (the core's ``MAX_DISTANCE_TERMS``).
MAX_DISTANCE_TERMS = 4096
#: The most monomials of the polynomial rest.
MAX_MONOMIALS = 512

LOG, POWER = 0, 1


@dataclass(frozen=True)
class DistanceTerms:
    """The terms of H = Σ_k w_k φ_k(r_k²) + P(x) as the core takes them.

    radial (K,): 0 for ln r², 1 for (r²)^power; weight, power (K,); dims (K,): D; first,
    second (K, 3): the coordinates of the two points (the first D columns); coeffs (M,),
    exponents (M, n): P. A second point of −1s is the origin.
    """

    radial: NDArray[np.int64]
    weight: NDArray[np.float64]
    power: NDArray[np.float64]
    dims: NDArray[np.int64]
    first: NDArray[np.int64]
    second: NDArray[np.int64]
    coeffs: NDArray[np.float64]
    exponents: NDArray[np.int64]

    def table(
        self,
    ) -> tuple[
        NDArray[np.int64],
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.int64],
        NDArray[np.int64],
        NDArray[np.int64],
        NDArray[np.float64],
        NDArray[np.int64],
    ]:
        """The core's ``distances`` argument."""
        return (self.radial, self.weight, self.power, self.dims, self.first, self.second,
                self.coeffs, self.exponents)  # fmt: skip

    def __len__(self) -> int:
        return int(self.radial.shape[0])


class _NotDistances(Exception):
    """The program is not a distance sum."""


class _Reader:
    def __init__(self, program: tuple[Node, ...], dim: int) -> None:
        self.program, self.dim = program, dim
        self.linear_memo: dict[int, dict[int, float]] = {}
        self.poly_memo: dict[int, dict[tuple[int, ...], float] | None] = {}

    def const(self, r: int) -> float | None:
        node = self.program[r]
        return float(node[1]) if node[0] == "const" else None

    def linear(self, r: int) -> dict[int, float]:
        """Register r as Σ w · leaf over sums, differences, negation and constant factors."""
        if r in self.linear_memo:
            return self.linear_memo[r]
        node = self.program[r]
        op = node[0]
        out: dict[int, float] = {}

        def add(parts: dict[int, float], scale: float) -> None:
            for k, w in parts.items():
                out[k] = out.get(k, 0.0) + scale * w

        if op in ("add", "sub"):
            add(self.linear(node[1]), 1.0)
            add(self.linear(node[2]), 1.0 if op == "add" else -1.0)
        elif op == "neg":
            add(self.linear(node[1]), -1.0)
        elif op == "mul" and self.const(node[1]) is not None:
            add(self.linear(node[2]), float(self.const(node[1])))  # type: ignore[arg-type]
        elif op == "mul" and self.const(node[2]) is not None:
            add(self.linear(node[1]), float(self.const(node[2])))  # type: ignore[arg-type]
        elif op == "div" and self.const(node[2]) not in (None, 0.0):
            add(self.linear(node[1]), 1.0 / float(self.const(node[2])))  # type: ignore[arg-type]
        else:
            out[r] = 1.0
        if len(out) > MAX_DISTANCE_TERMS + MAX_MONOMIALS:
            raise _NotDistances
        self.linear_memo[r] = out
        return out

    def polynomial(self, r: int) -> dict[tuple[int, ...], float] | None:
        """Register r as a polynomial {exponents: coefficient}, or None."""
        if r in self.poly_memo:
            return self.poly_memo[r]
        node = self.program[r]
        op = node[0]
        out: dict[tuple[int, ...], float] | None
        zero = (0,) * self.dim
        if op == "var":
            unit = [0] * self.dim
            unit[int(node[1])] = 1
            out = {tuple(unit): 1.0}
        elif op == "const":
            out = {zero: float(node[1])}
        elif op in ("add", "sub", "neg"):
            parts = [self.polynomial(k) for k in node[1:]]
            if any(p is None for p in parts):
                out = None
            else:
                out = dict(parts[0])  # type: ignore[arg-type]
                for p in parts[1:]:
                    for e, c in p.items():  # type: ignore[union-attr]
                        out[e] = out.get(e, 0.0) + (c if op == "add" else -c)
                if op == "neg":
                    out = {e: -c for e, c in out.items()}
        elif op == "mul":
            p, q = self.polynomial(node[1]), self.polynomial(node[2])
            out = None if p is None or q is None else _times(p, q)
        elif op == "div" and self.const(node[2]) not in (None, 0.0):
            p = self.polynomial(node[1])
            c = float(self.const(node[2]))  # type: ignore[arg-type]
            out = None if p is None else {e: v / c for e, v in p.items()}
        elif op == "powi" and int(node[2]) >= 0:
            p = self.polynomial(node[1])
            out = None if p is None else {zero: 1.0}
            for _ in range(int(node[2])):
                if out is None or p is None:
                    break
                out = _times(out, p)
        else:
            out = None
        if out is not None and len(out) > MAX_MONOMIALS:
            raise _NotDistances
        self.poly_memo[r] = out
        return out

    def difference(self, r: int) -> tuple[int, int] | None:
        """(i, j) where register r is ±(x_i − x_j), (i, −1) where it is ±x_i (the origin)."""
        parts = self.linear(r)
        if len(parts) == 1:
            ((k, w),) = parts.items()
            node = self.program[k]
            return (int(node[1]), -1) if node[0] == "var" and abs(w) == 1.0 else None
        if len(parts) != 2:
            return None
        (k1, w1), (k2, w2) = sorted(parts.items(), key=lambda kv: -kv[1])
        n1, n2 = self.program[k1], self.program[k2]
        if n1[0] != "var" or n2[0] != "var" or w1 != 1.0 or w2 != -1.0:
            return None
        return int(n1[1]), int(n2[1])

    def distance_square(self, r: int) -> tuple[float, list[tuple[int, int]]] | None:
        """(c, pairs) where register r is c Σ_d (x_{i_d} − x_{j_d})², c > 0, 1 ≤ D ≤ 3 (j_d = −1
        in every pair: the distance from the origin)."""
        parts = self.linear(r)
        if not 1 <= len(parts) <= MAX_POINT_DIM:
            return None
        scales = set(parts.values())
        if len(scales) != 1:
            return None
        c = scales.pop()
        if not c > 0.0:
            return None
        pairs = []
        for k in parts:
            node = self.program[k]
            if node[0] == "powi" and int(node[2]) == 2:
                d = self.difference(node[1])
            elif node[0] == "mul" and node[1] == node[2]:
                d = self.difference(node[1])
            else:
                d = None
            if d is None:
                return None
            pairs.append(d)
        if len({j == -1 for _, j in pairs}) != 1:
            return None  # a point minus the origin in some coordinates only
        return c, sorted(pairs)

    def radial(self, r: int) -> tuple[int, float, float, list[tuple[int, int]]] | None:
        """(kind, power, factor, pairs): register r is factor · φ(r²) (ln r²: factor ½ for
        ln r; a constant offset is dropped), or None."""
        node = self.program[r]
        op = node[0]
        if op == "log":
            inner = self.program[node[1]]
            half = inner[0] == "sqrt"
            q = self.distance_square(inner[1] if half else node[1])
            return None if q is None else (LOG, 0.0, 0.5 if half else 1.0, q[1])
        if op == "div" and self.const(node[1]) is not None:
            below = self.radial(node[2])
            if below is None or below[0] != POWER:
                return None
            return POWER, -below[1], float(self.const(node[1])) / below[2], below[3]  # type: ignore[arg-type]
        if op in ("sqrt", "powf", "powi"):
            p = 0.5 if op == "sqrt" else float(node[2])
            inner_node = self.program[node[1]]
            if inner_node[0] == "sqrt":  # (√(r²))^p = (r²)^{p/2}
                base, p = inner_node[1], p / 2
            else:
                base = node[1]
            q = self.distance_square(base)
            if q is None or p == 0.0:
                return None
            return POWER, p, q[0] ** p, q[1]
        q = self.distance_square(r)  # r² itself, as under 1/r²
        return None if q is None else (POWER, 1.0, q[0], q[1])


def _times(
    p: dict[tuple[int, ...], float], q: dict[tuple[int, ...], float]
) -> dict[tuple[int, ...], float]:
    out: dict[tuple[int, ...], float] = {}
    for e, c in p.items():
        for f, d in q.items():
            g = tuple(a + b for a, b in zip(e, f, strict=True))
            out[g] = out.get(g, 0.0) + c * d
            if len(out) > MAX_MONOMIALS:
                raise _NotDistances
    return out


def distance_terms(program: tuple[Node, ...], dim: int) -> DistanceTerms | None:
    """H's program (its value the last register) as a sum over distances plus a polynomial, or
    None where it is not one (or has no distance term: a polynomial H has its own paths)."""
    if not program:
        return None
    reader = _Reader(program, dim)
    rows: list[tuple[int, float, float, list[tuple[int, int]]]] = []
    poly: dict[tuple[int, ...], float] = {}
    try:
        for leaf, w in reader.linear(len(program) - 1).items():
            p = reader.polynomial(leaf)
            if p is not None:
                for e, c in p.items():
                    poly[e] = poly.get(e, 0.0) + w * c
                continue
            rad = reader.radial(leaf)
            if rad is None:
                return None
            kind, power, factor, pairs = rad
            rows.append((kind, w * factor, power, pairs))
    except (_NotDistances, RecursionError):
        return None
    if not rows or len(rows) > MAX_DISTANCE_TERMS or len(poly) > MAX_MONOMIALS:
        return None
    if not all(np.isfinite([w for _, w, _, _ in rows])):
        return None
    k = len(rows)
    first = np.zeros((k, MAX_POINT_DIM), dtype=np.int64)
    second = np.zeros((k, MAX_POINT_DIM), dtype=np.int64)
    for t, (_, _, _, pairs) in enumerate(rows):
        for d, (i, j) in enumerate(pairs):
            first[t, d], second[t, d] = i, j
    # The constant and zero monomials do not move the gradient.
    monomials = [(e, c) for e, c in poly.items() if any(e) and c != 0.0]
    return DistanceTerms(
        radial=np.array([r[0] for r in rows], dtype=np.int64),
        weight=np.array([r[1] for r in rows], dtype=np.float64),
        power=np.array([r[2] for r in rows], dtype=np.float64),
        dims=np.array([len(r[3]) for r in rows], dtype=np.int64),
        first=first,
        second=second,
        coeffs=np.array([c for _, c in monomials], dtype=np.float64),
        exponents=np.array([e for e, _ in monomials], dtype=np.int64).reshape(-1, dim),
    )
