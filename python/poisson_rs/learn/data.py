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

from ..files import describe_mode, read_input_bytes
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


#: Largest data file read (bytes on disk: a .npz, a .csv, or all the files of a Zarr store).
MAX_DATA_FILE_BYTES = 1 << 30
#: Largest decoded data (bytes of the arrays once decompressed): checked on the sizes a file
#: declares before anything is decompressed, so a small compressed file cannot grow past it.
MAX_DATA_BYTES = 1 << 29
#: Largest .csv read: its text is split into lines and parsed in memory, several times its size.
MAX_CSV_BYTES = 1 << 27
#: Most files in a Zarr store.
MAX_STORE_ENTRIES = 100_000
#: Largest system JSON file (``--system``) read.
MAX_SYSTEM_FILE_BYTES = 1 << 20


def load_trajectories(path: str | os.PathLike[str]) -> list[np.ndarray]:
    """Reads trajectories from ``.npz``, ``.csv`` or a Zarr directory → list of (n_i, dim).

    Untrusted input: only regular files (a FIFO would block, a device such as /dev/zero would
    never end) of at most :data:`MAX_DATA_FILE_BYTES` (:data:`MAX_CSV_BYTES` for a .csv),
    whose arrays declare at most :data:`MAX_DATA_BYTES` once decoded (checked before
    decompressing: a .npz of deflated zeros or a Zarr store declaring a huge shape is refused,
    not read). A Zarr store must be marked
    complete (an interrupted writer leaves missing chunks that would read as zeros). Raises
    FileNotFoundError when absent, ValueError naming the file and the problem otherwise."""
    p = Path(path)
    source = f"data file {os.fspath(path)}"
    if not os.path.lexists(p):
        raise FileNotFoundError(f"no data file {os.fspath(path)!r}")
    if p.is_dir():
        return _load_zarr(p, source)
    suffix = p.suffix.lower()
    if suffix == ".npz":
        raw = read_input_bytes(p, max_bytes=MAX_DATA_FILE_BYTES, what="data file")
        return _load_npz(raw, source)
    if suffix == ".csv":
        raw = read_input_bytes(p, max_bytes=MAX_CSV_BYTES, what="data file")
        return _load_csv(raw, source)
    raise ValueError(f"{source}: unknown format {suffix!r}; expected .npz, .csv or a Zarr dir")


def _check_declared(shape: tuple[int, ...], dtype: np.dtype, source: str, field: str) -> None:
    """Refuses an array whose declared shape and dtype hold more than :data:`MAX_DATA_BYTES`, or
    whose values are not real numbers, before it is read."""
    with parsing(source, field):
        if dtype.kind not in "fiub" or dtype.hasobject:
            raise ValueError(f"records must be real numbers, got dtype {dtype}")
        count = math.prod(int(d) for d in shape)
        if count * max(dtype.itemsize, 8) > MAX_DATA_BYTES:
            raise ValueError(
                f"declares shape {tuple(shape)} ({count} values), more than the "
                f"{MAX_DATA_BYTES // 8} values allowed"
            )


def _load_npz(raw: bytes, source: str) -> list[np.ndarray]:
    """The arrays of a .npz archive's bytes, each checked by its declared size first."""
    import io
    import zipfile

    with parsing(source, "npz arrays"):
        zf = zipfile.ZipFile(io.BytesIO(raw))
        infos = {i.filename.removesuffix(".npy"): i for i in zf.infolist()}
        if not infos:
            raise ValueError("holds no arrays")
        total = sum(i.file_size for i in infos.values())
        if total > MAX_DATA_BYTES:
            raise ValueError(
                f"its arrays take {total} bytes decompressed, more than the {MAX_DATA_BYTES} "
                "allowed"
            )
    names = list(infos)

    def array(name: str) -> np.ndarray:
        with parsing(source, name):
            with zf.open(infos[name]) as fh:
                version = np.lib.format.read_magic(fh)
                read_header = (
                    np.lib.format.read_array_header_1_0
                    if version == (1, 0)
                    else np.lib.format.read_array_header_2_0
                )
                shape, _, dtype = read_header(fh)
        _check_declared(shape, dtype, source, name)
        with parsing(source, name):
            with zf.open(infos[name]) as fh:
                # The zip member yields at most its declared size (checked above).
                return np.asarray(np.lib.format.read_array(fh, allow_pickle=False))

    if "trajectories" in names:
        return _split_array(array("trajectories"), source)
    ragged = [n for n in names if n.startswith("traj_")]
    if ragged:
        with parsing(source, "npz arrays"):
            ragged.sort(key=lambda s: int(s[5:]))
        return [np.asarray(array(n), dtype=np.float64) for n in ragged]
    if len(names) == 1:
        return _split_array(array(names[0]), source)
    raise ValueError(
        f"{source}: expected an array 'trajectories' or arrays 'traj_0', 'traj_1', ..., got "
        f"{names[:10]}"
    )


def _load_csv(raw: bytes, source: str) -> list[np.ndarray]:
    """Rows ``traj, μ_1..μ_n`` (or ``μ_1..μ_n``) after a header row."""
    import io

    with parsing(source, "csv rows"):
        lines = raw.decode("utf-8").splitlines()
        header = lines[0].strip().split(",") if lines else []
        body = [line for line in lines[1:] if line.strip()]
        if not body:
            raise ValueError("holds no records (a header row and no data)")
        table = np.loadtxt(io.StringIO("\n".join(body)), delimiter=",", ndmin=2)
    if header and header[0].strip().lower() == "traj":
        ids = table[:, 0]
        return [table[ids == i, 1:] for i in np.unique(ids)]
    return [table]


def _load_zarr(p: Path, source: str) -> list[np.ndarray]:
    """The ``trajectories`` array of a complete Zarr store, every file in it checked first."""
    _check_store_files(p, source)
    with parsing(source, "trajectories"):
        import zarr

        group = zarr.open_group(str(p), mode="r")
        attrs = dict(group.attrs)
    with parsing(source, "complete"):
        if attrs.get("complete") is not True:
            raise ValueError(
                "the store is not marked complete (its writer was interrupted, or it was not "
                "written by ensembles.to_zarr); missing chunks would read as zeros"
            )
    with parsing(source, "trajectories"):
        arr = group["trajectories"]
        if not isinstance(arr, zarr.Array):
            raise ValueError("is not an array")
        shape, chunks, dtype = tuple(arr.shape), tuple(arr.chunks), np.dtype(arr.dtype)
    _check_declared(shape, dtype, source, "trajectories")
    _check_declared(chunks, dtype, source, "trajectories chunks")
    with parsing(source, "trajectories"):
        data = np.asarray(arr[...])
    return _split_array(data, source)


def _check_store_files(root: Path, source: str) -> None:
    """Every entry of a Zarr store is a folder or a regular file (no link, FIFO or device), at
    most :data:`MAX_STORE_ENTRIES` of them and :data:`MAX_DATA_FILE_BYTES` in all."""
    import stat

    count, total = 0, 0
    for folder, dirs, files in os.walk(root, followlinks=False):
        for name in dirs + files:
            count += 1
            if count > MAX_STORE_ENTRIES:
                raise ValueError(f"{source}: more than {MAX_STORE_ENTRIES} files in the store")
            entry = Path(folder) / name
            st = os.lstat(entry)
            if stat.S_ISDIR(st.st_mode):
                continue
            if not stat.S_ISREG(st.st_mode):
                raise ValueError(
                    f"{source}: {entry.relative_to(root)} is {describe_mode(st.st_mode)}, not a "
                    "regular file"
                )
            total += st.st_size
            if total > MAX_DATA_FILE_BYTES:
                raise ValueError(
                    f"{source}: the store holds more than the {MAX_DATA_FILE_BYTES} bytes allowed"
                )


def read_system_file(path: str | os.PathLike[str], source: str) -> LiePoissonSystem:
    """A :class:`LiePoissonSystem` from a JSON file (its ``to_dict()``), read as untrusted input:
    a regular file of at most :data:`MAX_SYSTEM_FILE_BYTES`."""
    import json

    with parsing(source, "system"):
        raw = read_input_bytes(path, max_bytes=MAX_SYSTEM_FILE_BYTES, what="system file")
        spec = json.loads(raw.decode("utf-8"))
        if not isinstance(spec, dict):
            raise ValueError("must hold a JSON object (a system's to_dict())")
        return LiePoissonSystem.from_dict(spec)


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
    #: What the data must come from, for messages.
    source: str = "a Lie–Poisson system of this algebra"

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


def _from_tensor(x: Any) -> Any:
    """A torch tensor as a NumPy array (detached: one with requires_grad=True is data here)."""
    if type(x).__module__.startswith("torch") and hasattr(x, "detach"):
        return x.detach().cpu().numpy()
    return x


def _as_list(trajectories: Any) -> list[np.ndarray]:
    trajectories = _from_tensor(trajectories)
    if isinstance(trajectories, (str, os.PathLike)):
        return load_trajectories(trajectories)
    if isinstance(trajectories, np.ndarray) or (
        hasattr(trajectories, "shape") and hasattr(trajectories, "dtype")
    ):
        with parsing("trajectories"):
            arr = np.asarray(trajectories)
        if arr.dtype == object:
            return [_one(t, i) for i, t in enumerate(arr)]
        if arr.ndim == 3 and arr.shape[0] == 0:
            raise ValueError(f"trajectories: got no trajectories (shape {arr.shape})")
        return _split_array(arr, "trajectories")
    if isinstance(trajectories, Sequence) and not isinstance(trajectories, (str, bytes)):
        if len(trajectories) == 0:
            raise ValueError("trajectories: got an empty list")
        first = _from_tensor(trajectories[0])
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
    t = _from_tensor(t)
    if isinstance(t, Sequence):
        t = [_from_tensor(r) for r in t]
    try:
        arr = np.asarray(t, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(
            f"trajectories[{i}]: records must all have the same length (ragged records) and hold "
            f"real numbers ({exc})"
        ) from None
    return arr


#: The record spacings h accepted: the fits raise h to the power of the Taylor order (up to
#: 12) and divide by it, which must stay far from overflow and from subnormal numbers.
H_RANGE = (1e-12, 1e12)
#: The RMS |μ| of the data accepted: the Taylor series hold powers of μ up to the 20s.
SCALE_RANGE = (1e-12, 1e12)


def _check_h(h: Any) -> float:
    if isinstance(h, bool) or not isinstance(h, (int, float, np.floating, np.integer)):
        raise ValueError(f"h must be a real number, got {h!r}")
    try:
        hv = float(h)
    except OverflowError:
        raise ValueError(f"h must be finite and > 0, got {h!r} (overflows float64)") from None
    if not (math.isfinite(hv) and hv > 0):
        raise ValueError(f"h must be finite and > 0, got {hv}")
    lo, hi = H_RANGE
    if not lo <= hv <= hi:
        raise ValueError(
            f"h = {hv:g} is outside [{lo:g}, {hi:g}], where the fits' powers of h stay in "
            "floating-point range; rescale time (h and H together) to bring h within it"
        )
    return hv


def check_seed(seed: Any, name: str = "seed") -> int:
    """A seed: an integer in [0, 2**63)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"{name} must be an integer >= 0, got {seed!r}")
    if not 0 <= int(seed) < 2**63:
        raise ValueError(f"{name} must be an integer in [0, 2**63), got {seed!r}")
    return int(seed)


def _check_fraction(test_fraction: Any) -> float:
    if isinstance(test_fraction, bool) or not isinstance(
        test_fraction, (int, float, np.floating, np.integer)
    ):
        raise ValueError(f"test_fraction must be a number in [0, 1), got {test_fraction!r}")
    f = float(test_fraction)
    if not 0 <= f < 1:
        raise ValueError(f"test_fraction must lie in [0, 1), got {test_fraction!r}")
    return f


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


#: How far noise alone moves the relative Casimir drift, per unit of relative noise level σ̂:
#: a quadratic Casimir's change between two records is 2√2·σ̂ (relative) per standard
#: deviation, and the largest of up to 10⁵ records about 5 of them; with room to spare.
NOISE_DRIFT_FACTOR = 30.0
#: A drift beyond what noise explains by this factor, and at least :data:`DRIFT_REFUSE`
#: relative, is refused by :func:`poisson_rs.learn` (the data are not Lie–Poisson).
DRIFT_REFUSE_RATIO = 10.0
DRIFT_REFUSE = 1e-2


def drift_limit(noise: float) -> float:
    """The relative Casimir drift noise of relative level ``noise`` explains (the fixed
    :data:`CASIMIR_DRIFT_TOL` where the noise is unknown)."""
    if not math.isfinite(noise):
        return CASIMIR_DRIFT_TOL
    return max(NOISE_DRIFT_FACTOR * noise, 1e-10)


def prepare(
    trajectories: Any,
    h: Any,
    algebra: LieAlgebra | None,
    *,
    test_fraction: float = 0.2,
    seed: int = 0,
    name: str = "trajectories",
    system: Any = None,
) -> TrajectoryData:
    """Validates and splits ``trajectories`` (see the module docstring) for ``algebra``, or for
    the structure of ``system`` (any :class:`poisson_rs.PoissonSystem`; its H is not used):
    then its dimension, its domain (:meth:`~poisson_rs.PoissonSystem.check_states`) and its
    Casimirs are the ones checked.

    Raises one ValueError naming the input and field for: h ≤ 0, not finite or outside
    :data:`H_RANGE`, no trajectories or no records, NaN/inf, ragged records within a
    trajectory, a dimension other than the algebra's, fewer than two records, an RMS |μ|
    outside :data:`SCALE_RANGE` (or zero), records that do not move (an equilibrium), a split
    that leaves nothing to train on. Warns (CasimirDriftWarning) when the known Casimirs drift
    by more than the data's noise level explains (:func:`drift_limit`). Held-out trajectories
    are chosen by ``seed``; with a single trajectory its last ``test_fraction`` of records is
    held out instead (nothing is held out where that leaves fewer than two records either side:
    ``TrajectoryData.test`` is then empty).
    """
    hv = _check_h(h)
    test_fraction = _check_fraction(test_fraction)
    seed = check_seed(seed)
    trajs = _as_list(trajectories)
    if not trajs:
        raise ValueError(f"{name}: got no trajectories")
    if system is None:
        assert algebra is not None
        system = LiePoissonSystem(algebra, _zero_polynomial(algebra.dim))
        what = f"the algebra {algebra.name or ''}"
        source = "a Lie–Poisson system of this algebra"
        casimirs_of = f"the Casimirs of {algebra.name or 'the algebra'}"
    else:
        what = f"the structure ({system.title})"
        source = "a Hamiltonian system on this structure"
        casimirs_of = "the structure's Casimirs"
    n = system.dim
    clean = []
    for i, t in enumerate(trajs):
        t = np.asarray(t)
        if t.dtype.kind not in "fiub":
            raise ValueError(f"{name}[{i}]: records must be real numbers, got dtype {t.dtype}")
        if t.ndim != 2:
            raise ValueError(
                f"{name}[{i}]: a trajectory must be (n_records, dim), got shape {t.shape} (ragged "
                "records?)"
            )
        if t.shape[1] != n:
            raise ValueError(
                f"{name}[{i}]: records have dimension {t.shape[1]}, but {what} has dimension {n}"
            )
        if t.shape[0] < 2:
            raise ValueError(f"{name}[{i}]: needs at least two records, got {t.shape[0]}")
        t = np.asarray(t, dtype=np.float64)
        if not np.isfinite(t).all():
            bad = np.argwhere(~np.isfinite(t))[0]
            raise ValueError(
                f"{name}[{i}]: record {bad[0]}, component {bad[1]} is {t[bad[0], bad[1]]} (data "
                "must be finite)"
            )
        if hasattr(system, "check_states"):
            system.check_states(t, name=f"{name}[{i}]")
        clean.append(np.ascontiguousarray(t, dtype=np.float64))
    allx = np.concatenate(clean)
    # RMS |μ| computed in units of the largest entry: no overflow or underflow on the way.
    big = float(np.max(np.abs(allx)))
    if big == 0.0:
        raise ValueError(f"{name}: every record is zero (an equilibrium): nothing to learn")
    scale = big * float(np.sqrt(np.mean(np.sum((allx / big) ** 2, axis=1))))
    lo, hi = SCALE_RANGE
    if not lo <= scale <= hi:
        raise ValueError(
            f"{name}: the records' RMS |μ| is {scale:.3g}, outside [{lo:g}, {hi:g}] where the "
            "fits' powers of μ stay in floating-point range; rescale the data"
        )
    r = np.linalg.norm(allx, axis=1)
    motion = max(float(np.max(np.abs(np.diff(t, axis=0)))) for t in clean) / scale
    if motion <= 1e-12:
        raise ValueError(
            f"{name}: the records do not move (largest change between consecutive records "
            f"{motion:.2g} of the RMS |μ|): data at an equilibrium tell nothing about H"
        )
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
        if n_test >= len(clean):
            raise ValueError(
                f"test_fraction = {test_fraction:g} holds out {n_test} of {len(clean)} "
                "trajectories, leaving none to train on"
            )
        test = [clean[i] for i in sorted(order[:n_test])]
        train = [clean[i] for i in sorted(order[n_test:])]
    drift = casimir_drift(system, clean)
    noise = estimate_noise(clean) / scale
    limit = drift_limit(noise)
    if math.isfinite(drift) and drift > limit:
        explained = (
            f"the data's noise level {noise:.2g} explains up to {limit:.2g}"
            if math.isfinite(noise)
            else f"the noise level cannot be told (too few records), tolerance {limit:.2g}"
        )
        warnings.warn(
            f"{name}: {casimirs_of} drift by up to {drift:.3g} (relative) along a "
            f"trajectory, where {explained}; these data cannot all come from {source} "
            "(another structure, forcing or damping), and a learned Poisson map keeps the "
            "Casimirs exactly",
            CasimirDriftWarning,
            stacklevel=3,
        )
    digest = hashlib.sha256()
    for t in clean:
        digest.update(np.asarray(t.shape, dtype=np.int64).tobytes())
        digest.update(t.tobytes())
    return TrajectoryData(
        train=train,
        test=test,
        h=hv,
        dim=n,
        noise=noise,
        scale=scale,
        casimir_drift=drift,
        digest=digest.hexdigest(),
        shape=(len(clean), max(len(t) for t in clean), n),
        lo=allx.min(0),
        hi=allx.max(0),
        radius=(float(r.min()), float(r.max())),
        source=source,
    )


def _zero_polynomial(n: int) -> Any:
    from ..structures.lie_poisson import Polynomial

    return Polynomial({(0,) * n: 0.0})


def refuse_drift(data: TrajectoryData) -> None:
    """ValueError when the data's Casimirs drift far beyond what their noise explains: they do
    not come from a Lie–Poisson system of the algebra (damping, forcing, another structure),
    and no Poisson integrator, which keeps every Casimir, can fit them."""
    drift, limit = data.casimir_drift, drift_limit(data.noise)
    if not (math.isfinite(drift) and math.isfinite(data.noise)):
        return
    if drift > max(DRIFT_REFUSE, DRIFT_REFUSE_RATIO * limit):
        raise ValueError(
            f"trajectories: the Casimirs drift by up to {drift:.3g} (relative) along a "
            f"trajectory, {drift / limit:.3g}× what the data's noise level {data.noise:.2g} "
            f"explains: these data do not come from {data.source} (damping, forcing or "
            "another structure), and a Poisson integrator keeps every Casimir, so none can "
            "fit them"
        )
