"""A family of Poisson bivectors π_θ(x) = Σ_a θ_a Π_a(x), linear in θ, as structure discovery
(``pr.learn(..., structure="discover")``) searches it.

Each term Π_a is one monomial x^{e_a} in the entry (i_a, j_a) and its negative in (j_a, i_a), so
every family a structure offers (log-canonical c_ij x_i x_j, Lie–Poisson Σ_k c_ijk x_k, affine,
polynomial of a degree) is a list of (i, j, e) and a builder that turns θ into the structure's
own system. The generic work sits here: the bivector and its derivatives at states, the Jacobi
identity's residual (quadratic in θ) and the least-norm projection onto it, the bracket as text.
What θ means to a structure, and which system it becomes, is the structure's business (its
module's ``BRACKET_FAMILIES`` table): this module names none.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["JACOBI_RTOL", "BracketFamily"]

FloatArray = NDArray[np.float64]
Term = tuple[int, int, tuple[int, ...]]

#: A projected bracket's Jacobi residual must be below this, relative to Σ|π||∂π| at the
#: check points (both scale as π²): what the structures' own checks accept.
JACOBI_RTOL = 1e-13
#: Gauss–Newton iterates of the projection onto the Jacobi variety.
PROJECTION_ITER = 60


class BracketFamily:
    """π_θ(x)_ij = Σ_a θ_a x^{e_a} [i_a = i, j_a = j] − (same with i, j swapped).

    Parameters
    ----------
    name : str
        Short name in reports ("log-canonical", "lie-poisson", "affine", "poly2").
    dim : int
    terms : sequence of (i, j, e), i < j, e a tuple of ``dim`` non-negative exponents
    build : callable θ → system
        The structure's system with the bracket π_θ and H = 0 (its ``hamiltonian_family``
        gives the Hamiltonians fitted on it). Raises ValueError when θ is not admissible.
    description : str
        What the family is, for reports ("π_ij = c_ij x_i x_j, c constant").
    jacobi_free : bool
        True where every θ obeys Jacobi (a constant c in log-canonical coordinates): no
        projection is needed.
    domain : callable states → str or None, optional
        Why the family cannot describe states (e.g. "a state is not in the positive orthant"),
        or None where it can.
    template : array_like, optional
        A θ the builder accepts, whose system supplies the Hamiltonian family during the
        search (the family's gradients do not depend on θ); default zeros.
    """

    def __init__(
        self,
        name: str,
        dim: int,
        terms: Sequence[Term],
        *,
        build: Callable[[FloatArray], Any],
        description: str,
        jacobi_free: bool = False,
        domain: Callable[[FloatArray], str | None] | None = None,
        template: Any = None,
    ) -> None:
        self.name, self.dim, self.description = name, dim, description
        self.terms: list[Term] = [(int(i), int(j), tuple(int(v) for v in e)) for i, j, e in terms]
        if not self.terms or any(
            not 0 <= i < j < dim or len(e) != dim or min(e) < 0 for i, j, e in self.terms
        ):
            raise ValueError(f"bracket terms must be (i < j < {dim}, {dim} exponents ≥ 0)")
        self._build, self.jacobi_free, self._domain = build, jacobi_free, domain
        self._template = (
            np.zeros(len(self.terms)) if template is None else np.asarray(template, np.float64)
        )
        self._exps = np.array([e for _, _, e in self.terms], dtype=np.int64)  # (P, n)

    @property
    def degree(self) -> int:
        """The largest total degree of an entry."""
        return max(sum(e) for _, _, e in self.terms)

    def jacobi_points(self, lo: Any, hi: Any, seed: int = 0) -> FloatArray:
        """Seeded generic points in the box [lo, hi] that decide the Jacobi identity: J is a
        polynomial of degree 2·degree − 1, so twice as many points as it has coefficients
        (at least 48). Trajectory states would not do: they lie on curves."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        deg = max(2 * self.degree - 1, 0)
        count = max(48, 2 * math.comb(self.dim + deg, self.dim))
        mid, half = (
            (lo + hi) / 2,
            np.maximum((hi - lo) / 2, 1e-3 * (np.abs(lo) + np.abs(hi)) + 1e-12),
        )
        rng = np.random.default_rng(seed)
        return mid + half * rng.uniform(-1.0, 1.0, size=(count, self.dim))

    def __len__(self) -> int:
        return len(self.terms)

    def __repr__(self) -> str:
        return f"BracketFamily({self.name!r}, dim={self.dim}, size={len(self)})"

    def applies(self, states: FloatArray) -> str | None:
        """Why this family cannot describe ``states`` (n-vectors), or None."""
        return None if self._domain is None else self._domain(states)

    def system(self, theta: Any) -> Any:
        """The structure's system with bracket π_θ and H = 0."""
        return self._build(np.asarray(theta, dtype=np.float64))

    def template_system(self) -> Any:
        """A system of the family (θ = ``template``): its Hamiltonian family for the search."""
        return self._build(self._template)

    def _monomials(self, x: FloatArray) -> FloatArray:
        """x^{e_a}, (B, P)."""
        return np.prod(x[:, None, :] ** self._exps[None, :, :], axis=2)

    def basis(self, x: Any) -> FloatArray:
        """Π_a(x), (B, n, n, P) for states x (B, n)."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        m = self._monomials(x)
        out = np.zeros((x.shape[0], self.dim, self.dim, len(self)))
        for a, (i, j, _) in enumerate(self.terms):
            out[:, i, j, a] = m[:, a]
            out[:, j, i, a] = -m[:, a]
        return out

    def basis_derivative(self, x: Any) -> FloatArray:
        """∂_l Π_a(x)_ij as (B, n, n, n, P) indexed [b, i, j, l, a]."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        out = np.zeros((x.shape[0], self.dim, self.dim, self.dim, len(self)))
        for a, (i, j, e) in enumerate(self.terms):
            for ell in range(self.dim):
                if e[ell] == 0:
                    continue
                d = list(e)
                d[ell] -= 1
                v = e[ell] * np.prod(x ** np.array(d)[None, :], axis=1)
                out[:, i, j, ell, a] = v
                out[:, j, i, ell, a] = -v
        return out

    def bivector(self, x: Any, theta: Any) -> FloatArray:
        """π_θ(x), (B, n, n)."""
        return self.basis(x) @ np.asarray(theta, dtype=np.float64)

    def _jacobi_parts(
        self, theta: FloatArray, pb: FloatArray, db: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """J_ijk = Σ_l π_il ∂_l π_jk + cyclic at the points of ``pb``/``db`` (values and
        derivatives of the basis), its Jacobian in θ, and the scale Σ|π_il||∂_l π_jk| + cyclic."""
        pi = pb @ theta  # (B, n, n)
        dpi = db @ theta  # (B, n, n, n): [b, j, k, l]
        j = np.zeros(pi.shape[:1] + (self.dim,) * 3)
        jac = np.zeros((*j.shape, len(self)))
        scale = np.zeros(j.shape)
        for perm in ("ijk", "jki", "kij"):
            a, b, c = perm
            j += np.einsum(f"x{a}l,x{b}{c}l->xijk", pi, dpi)
            jac += np.einsum(f"x{a}lp,x{b}{c}l->xijkp", pb, dpi)
            jac += np.einsum(f"x{a}l,x{b}{c}lp->xijkp", pi, db)
            scale += np.einsum(f"x{a}l,x{b}{c}l->xijk", np.abs(pi), np.abs(dpi))
        return j.reshape(-1), jac.reshape(-1, len(self)), scale.reshape(-1)

    def jacobi_residual(self, theta: Any, points: Any) -> float:
        """max |J_ijk| / max(Σ|π||∂π|) at ``points`` (B, n): 0 for a Poisson bivector (a
        polynomial identity, so enough generic points decide it)."""
        theta = np.asarray(theta, dtype=np.float64)
        if self.jacobi_free:
            return 0.0
        pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
        j, _, scale = self._jacobi_parts(theta, self.basis(pts), self.basis_derivative(pts))
        top = float(np.max(scale)) if scale.size else 0.0
        return float(np.max(np.abs(j))) / top if top > 0 else 0.0

    def project(
        self, theta: Any, points: Any, free: Any = None, support: Any = None
    ) -> tuple[FloatArray, float]:
        """The nearest θ (least-norm Gauss–Newton steps) whose bracket obeys Jacobi at
        ``points``, and its relative residual (:meth:`jacobi_residual`). ``free`` (P, k):
        directions θ may move along at (almost) no cost, e.g. those the data cannot see;
        ``support`` (indices): the only coefficients that may move (default all)."""
        theta = np.array(theta, dtype=np.float64)
        f = np.zeros((len(self), 0)) if free is None else np.asarray(free, np.float64)
        keep = np.ones(len(self)) if support is None else np.isin(np.arange(len(self)), support)
        if self.jacobi_free:
            return theta, 0.0
        pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
        pb, db = self.basis(pts), self.basis_derivative(pts)

        def measure(th: FloatArray) -> tuple[FloatArray, FloatArray, float, float]:
            j, jac, scale = self._jacobi_parts(th, pb, db)
            top = float(np.max(scale)) if scale.size else 0.0
            if top <= 0:
                return j, jac, 0.0, 0.0
            return j, jac, float(np.max(np.abs(j))) / top, float(np.linalg.norm(j)) / top

        j, jac, res, cost = measure(theta)
        best, best_res = theta.copy(), res
        for _ in range(PROJECTION_ITER):
            if res <= JACOBI_RTOL * 1e-2:
                break
            # Moving along ``free`` costs 1e-6 of moving elsewhere (columns scaled by 1e3).
            aug = np.concatenate([jac * keep, 1e3 * (jac @ f)], axis=1)
            # J is homogeneous (θ = 0 solves it): the step keeps θ's component along itself,
            # so the residual falls relative to θ² and not by shrinking θ.
            along = np.concatenate([theta, 1e3 * (theta @ f)]) / max(
                float(np.linalg.norm(theta)), 1e-300
            )
            weight = float(np.linalg.norm(jac)) + 1.0
            aug = np.vstack([aug, weight * along])
            step, *_ = np.linalg.lstsq(aug, np.concatenate([-j, [0.0]]), rcond=1e-12)
            move = keep * step[: len(self)] + 1e3 * (f @ step[len(self) :])
            lam = 1.0
            while lam >= 1.0 / 256:
                trial = measure(theta + lam * move)
                if trial[3] < cost:
                    break
                lam /= 2
            else:
                break
            theta = theta + lam * move
            j, jac, res, cost = trial
            if res < best_res:
                best, best_res = theta.copy(), res
        return best, best_res

    def jacobi_in_subspace(
        self, theta: Any, directions: Any, points: Any, seed: int = 0, starts: int = 8
    ) -> tuple[FloatArray, float]:
        """The θ + D z (D = ``directions``, (P, k)) closest to obeying Jacobi at ``points``:
        Gauss–Newton on z alone from the least-norm point and ``starts`` seeded random ones
        (J is quadratic in z, with local minima), the best kept; and its relative residual.
        Moving along the directions the data cannot see changes no fitted field."""
        theta = np.asarray(theta, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
        if self.jacobi_free or d.shape[1] == 0:
            return theta.copy(), self.jacobi_residual(theta, pts)
        pb, db = self.basis(pts), self.basis_derivative(pts)

        def parts(z: Any) -> tuple[FloatArray, FloatArray, float]:
            j, jac, scale = self._jacobi_parts(theta + d @ z, pb, db)
            top = float(np.max(scale)) if scale.size else 0.0
            return j, jac @ d, top

        rng = np.random.default_rng(seed)
        size = float(np.linalg.norm(theta))
        zs: list[Any] = [np.zeros(d.shape[1])]
        zs += [size * rng.normal(size=d.shape[1]) for _ in range(starts)]
        best, best_res = theta.copy(), self.jacobi_residual(theta, pts)
        for z in zs:
            j, jz, top = parts(z)
            for _ in range(PROJECTION_ITER):
                cost = float(np.linalg.norm(j))
                step, *_ = np.linalg.lstsq(jz, -j, rcond=1e-12)
                lam = 1.0
                while lam >= 1.0 / 1024:
                    trial = parts(z + lam * step)
                    if float(np.linalg.norm(trial[0])) < cost:
                        break
                    lam /= 2
                else:
                    break
                z = z + lam * step
                j, jz, top = trial
            res = float(np.max(np.abs(j))) / top if top > 0 else math.inf
            if res < best_res:
                best, best_res = theta + d @ z, res
        return best, best_res

    def text(self, theta: Any, names: Sequence[str], digits: int = 10) -> str:
        """The bracket as formulas, one per non-zero entry above the diagonal:
        "{u, v} = 1.0*u*v"."""
        theta = np.asarray(theta, dtype=np.float64)
        entries: dict[tuple[int, int], list[str]] = {}
        for (i, j, e), t in zip(self.terms, theta, strict=True):
            if t == 0.0:
                continue
            mono = "*".join(f"{names[k]}**{p}" if p > 1 else names[k] for k, p in enumerate(e) if p)
            coef = f"{t:.{digits}g}"
            entries.setdefault((i, j), []).append(f"{coef}*{mono}" if mono else coef)
        if not entries:
            return "π = 0"
        return "; ".join(
            f"{{{names[i]}, {names[j]}}} = " + " + ".join(parts).replace("+ -", "- ")
            for (i, j), parts in sorted(entries.items())
        )
