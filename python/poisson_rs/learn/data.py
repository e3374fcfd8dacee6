"""Trajectory data for :func:`poisson_rs.learn`: loading, validation, splitting, diagnostics.

Trajectories are records h apart: an array (n_traj, n_records, dim), one (n_records, dim) array,
or a list of (n_records_i, dim) arrays (ragged lengths allowed between trajectories). Files:
``.npz`` (an array named ``trajectories``, or the only array in the file, or ``traj_0``,
``traj_1``, ... for ragged data), ``.csv`` (columns ``traj, μ_1..μ_n`` with a header row, or
``μ_1..μ_n`` for a single trajectory) and a Zarr group written by
:func:`poisson_rs.ensembles.to_zarr` (its ``trajectories`` array).
"""

from __future__ import annotations

import hashlib
import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..structures.lie_poisson import LieAlgebra, LiePoissonSystem
from ..untrusted import parsing

__all__ = [
    "CasimirDriftWarning",
    "HullWarning",
    "TrajectoryData",
    "load_trajectories",
    "prepare",
]

#: Relative Casimir drift along a trajectory above which the data are flagged.
CASIMIR_DRIFT_TOL = 1e-6


class CasimirDriftWarning(UserWarning):
    """The data's Casimirs drift: they cannot all come from a Lie–Poisson flow of this algebra."""


class HullWarning(UserWarning):
    """States to be integrated lie outside the region the data covered."""


def load_trajectories(path: str | os.PathLike[str]) -> list[np.ndarray]:
    """Reads trajectories from ``.npz``, ``.csv`` or a Zarr directory → list of (n_i, dim)."""
    p = Path(path)
    source = f"data file {os.fspath(path)}"
    if not p.exists():
        raise FileNotFoundError(f"no data file {os.fspath(path)!r}")
    if p.is_dir():
        with parsing(source, "trajectories"):
            import zarr

            arr = np.asarray(zarr.open_group(str(p), mode="r")["trajectories"][...])
        return _split_array(arr, source)
    suffix = p.suffix.lower()
    if suffix == ".npz":
        with parsing(source, "npz arrays"), np.load(p, allow_pickle=False) as z:
            names = list(z.files)
            if "trajectories" in names:
                return _split_array(np.asarray(z["trajectories"]), source)
            ragged = sorted((n for n in names if n.startswith("traj_")), key=lambda s: int(s[5:]))
            if ragged:
                return [np.asarray(z[n], dtype=np.float64) for n in ragged]
            if len(names) == 1:
                return _split_array(np.asarray(z[names[0]]), source)
            raise ValueError(
                f"expected an array 'trajectories' or arrays 'traj_0', 'traj_1', ..., got {names}"
            )
    if suffix == ".csv":
        with parsing(source, "csv rows"):
            with open(p, encoding="utf-8") as fh:
                header = fh.readline().strip().split(",")
            table = np.loadtxt(p, delimiter=",", skiprows=1, ndmin=2)
        if header and header[0].strip().lower() == "traj":
            ids = table[:, 0]
            return [table[ids == i, 1:] for i in np.unique(ids)]
        return [table]
    raise ValueError(f"{source}: unknown format {suffix!r}; expected .npz, .csv or a Zarr dir")


def _split_array(arr: np.ndarray, source: str) -> list[np.ndarray]:
    if arr.ndim == 2:
        return [arr]
    if arr.ndim == 3:
        return list(arr)
    raise ValueError(f"{source}: trajectories must have 2 or 3 dimensions, got shape {arr.shape}")


@dataclass
class TrajectoryData:
    """Validated trajectories, split into training and held-out ones.

    ``train`` and ``test`` are lists of (n_i, dim) float64 arrays; ``h`` the record spacing;
    ``noise`` the estimated noise level relative to the data's scale (NaN where it cannot be
    told: fewer than 8 records per trajectory); ``scale`` the RMS of |μ|; ``casimir_drift``
    the largest relative drift of the algebra's known Casimirs along a trajectory (NaN when
    none is known); ``digest`` a SHA-256 of the data; ``shape`` (n_traj, max records, dim).
    """

    train: list[np.ndarray]
    test: list[np.ndarray]
    h: float
    dim: int
    noise: float
    scale: float
    casimir_drift: float
    digest: str
    shape: tuple[int, int, int]
    lo: np.ndarray = field(repr=False)
    hi: np.ndarray = field(repr=False)
    radius: tuple[float, float] = (0.0, math.inf)

    def pairs(self, which: str = "train") -> tuple[np.ndarray, np.ndarray]:
        """(μ_k, μ_{k+1}) stacked over ``which`` ("train", "test" or "all") → (m, dim) each."""
        trajs = self._which(which)
        a = [t[:-1] for t in trajs]
        b = [t[1:] for t in trajs]
        return np.concatenate(a), np.concatenate(b)

    def _which(self, which: str) -> list[np.ndarray]:
        return {"train": self.train, "test": self.test, "all": self.train + self.test}[which]

    def outside_hull(self, states: Any, margin: float = 0.1) -> np.ndarray:
        """Mask of states (m, dim) outside the data's box widened by ``margin`` of its size, or
        with |μ| outside the data's range of |μ| widened likewise."""
        x = np.asarray(states, dtype=np.float64).reshape(-1, self.dim)
        width = self.hi - self.lo
        lo, hi = self.lo - margin * width, self.hi + margin * width
        r = np.linalg.norm(x, axis=1)
        r_lo, r_hi = self.radius
        span = r_hi - r_lo
        return (
            (x < lo).any(1)
            | (x > hi).any(1)
            | (r < r_lo - margin * span - 1e-12 * r_hi)
            | (r > r_hi + margin * span + 1e-12 * r_hi)
        )

    def warn_outside(self, states: Any) -> int:
        """Warns (HullWarning) when states leave the data's hull; returns how many did."""
        n = int(self.outside_hull(states).sum())
        if n:
            warnings.warn(
                f"{n} state(s) to be integrated lie outside the region the data covered; the "
                "learned model extrapolates there",
                HullWarning,
                stacklevel=3,
            )
        return n


def _as_list(trajectories: Any) -> list[np.ndarray]:
    if isinstance(trajectories, (str, os.PathLike)):
        return load_trajectories(trajectories)
    if isinstance(trajectories, np.ndarray) or (
        hasattr(trajectories, "shape") and hasattr(trajectories, "dtype")
    ):
        arr = np.asarray(trajectories)
        if arr.dtype == object:
            return [_one(t, i) for i, t in enumerate(arr)]
        return _split_array(arr, "trajectories")
    if isinstance(trajectories, Sequence) and not isinstance(trajectories, (str, bytes)):
        if len(trajectories) == 0:
            raise ValueError("trajectories: got an empty list")
        first = trajectories[0]
        try:
            depth = np.ndim(first)
        except ValueError:  # numpy refuses ragged nesting
            depth = 2
        if depth == 1:  # one trajectory given as a list of records
            return [_one(trajectories, 0)]
        return [_one(t, i) for i, t in enumerate(trajectories)]
    raise TypeError(
        "trajectories must be an array (n_traj, n_records, dim), a list of (n_records, dim) "
        f"arrays or a path, got {type(trajectories).__name__}"
    )


def _one(t: Any, i: int) -> np.ndarray:
    try:
        arr = np.asarray(t, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"trajectories[{i}]: records must all have the same length (ragged records) and hold "
            f"real numbers ({exc})"
        ) from None
    return arr


def _check_h(h: Any) -> float:
    if isinstance(h, bool) or not isinstance(h, (int, float, np.floating, np.integer)):
        raise ValueError(f"h must be a real number, got {h!r}")
    hv = float(h)
    if not (math.isfinite(hv) and hv > 0):
        raise ValueError(f"h must be finite and > 0, got {hv}")
    return hv


def estimate_noise(trajs: Sequence[np.ndarray], order: int = 6) -> float:
    """Noise level (standard deviation per coordinate, absolute) from the ``order``-th finite
    differences along each trajectory: for white noise of std σ they have std σ·√C(2k, k), while a
    smooth signal's shrink as h^k. Robust (median absolute deviation). NaN when no trajectory
    has order + 1 records. Biased high by the signal's own h^k f^(k) term: an upper bound."""
    diffs = [np.diff(t, n=order, axis=0).ravel() for t in trajs if len(t) > order]
    if not diffs:
        return math.nan
    d = np.concatenate(diffs)
    mad = float(np.median(np.abs(d - np.median(d)))) * 1.4826
    return mad / math.sqrt(math.comb(2 * order, order))


def casimir_drift(system: LiePoissonSystem, trajs: Sequence[np.ndarray]) -> float:
    """Largest |C(μ_k) − C(μ_0)| / max(|C|, |μ|^deg) over trajectories and known Casimirs (NaN
    when the algebra has none known)."""
    worst = 0.0
    for t in trajs:
        c = system.casimirs(t)
        if c is None:
            return math.nan
        scale = max(float(np.max(np.abs(c))), float(np.max(np.sum(t * t, 1))), 1e-300)
        worst = max(worst, float(np.max(np.abs(c - c[:1]))) / scale)
    return worst


def prepare(
    trajectories: Any,
    h: Any,
    algebra: LieAlgebra,
    *,
    test_fraction: float = 0.2,
    seed: int = 0,
    name: str = "trajectories",
) -> TrajectoryData:
    """Validates and splits ``trajectories`` (see the module docstring) for ``algebra``.

    Raises one ValueError naming the input and field for: h ≤ 0 or not finite, NaN/inf, ragged
    records within a trajectory, a dimension other than the algebra's, fewer than two records.
    Warns (CasimirDriftWarning) when the known Casimirs drift by more than
    :data:`CASIMIR_DRIFT_TOL` relative. Held-out trajectories are chosen by ``seed``; with a
    single trajectory its last ``test_fraction`` of records is held out instead.
    """
    hv = _check_h(h)
    trajs = _as_list(trajectories)
    n = algebra.dim
    clean = []
    for i, t in enumerate(trajs):
        if t.dtype.kind not in "fiu":
            raise ValueError(f"{name}[{i}]: records must be real numbers, got dtype {t.dtype}")
        if t.ndim != 2:
            raise ValueError(
                f"{name}[{i}]: a trajectory must be (n_records, dim), got shape {t.shape} (ragged "
                "records?)"
            )
        if t.shape[1] != n:
            raise ValueError(
                f"{name}[{i}]: records have dimension {t.shape[1]}, but the algebra "
                f"{algebra.name or ''} has dimension {n}"
            )
        if t.shape[0] < 2:
            raise ValueError(f"{name}[{i}]: needs at least two records, got {t.shape[0]}")
        if not np.isfinite(t).all():
            bad = np.argwhere(~np.isfinite(t))[0]
            raise ValueError(
                f"{name}[{i}]: record {bad[0]}, component {bad[1]} is {t[bad[0], bad[1]]} (data "
                "must be finite)"
            )
        clean.append(np.ascontiguousarray(t, dtype=np.float64))
    if not 0 <= test_fraction < 1:
        raise ValueError(f"test_fraction must lie in [0, 1), got {test_fraction}")
    rng = np.random.default_rng(seed)
    if len(clean) == 1:
        t = clean[0]
        n_test = round(test_fraction * len(t))
        if n_test >= 2 and len(t) - n_test >= 2:
            train, test = [t[: len(t) - n_test]], [t[len(t) - n_test - 1 :]]
        else:
            train, test = [t], []
    else:
        order = rng.permutation(len(clean))
        n_test = round(test_fraction * len(clean))
        test = [clean[i] for i in sorted(order[:n_test])]
        train = [clean[i] for i in sorted(order[n_test:])]
    allx = np.concatenate(clean)
    system = LiePoissonSystem(algebra, _zero_polynomial(n))
    drift = casimir_drift(system, clean)
    if math.isfinite(drift) and drift > CASIMIR_DRIFT_TOL:
        warnings.warn(
            f"{name}: the Casimirs of {algebra.name or 'the algebra'} drift by up to {drift:.3g} "
            "(relative) along a trajectory; these data cannot all come from a Lie–Poisson system "
            "of this algebra (noise, another structure or forcing), and a learned Poisson map "
            "keeps them exactly",
            CasimirDriftWarning,
            stacklevel=3,
        )
    digest = hashlib.sha256()
    for t in clean:
        digest.update(np.asarray(t.shape, dtype=np.int64).tobytes())
        digest.update(t.tobytes())
    r = np.linalg.norm(allx, axis=1)
    scale = float(np.sqrt(np.mean(r * r))) or 1.0
    return TrajectoryData(
        train=train,
        test=test,
        h=hv,
        dim=n,
        noise=estimate_noise(clean) / scale,
        scale=scale,
        casimir_drift=drift,
        digest=digest.hexdigest(),
        shape=(len(clean), max(len(t) for t in clean), n),
        lo=allx.min(0),
        hi=allx.max(0),
        radius=(float(r.min()), float(r.max())),
    )


def _zero_polynomial(n: int) -> Any:
    from ..structures.lie_poisson import Polynomial

    return Polynomial({(0,) * n: 0.0})
