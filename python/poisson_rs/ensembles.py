"""Ensembles beyond one process: rollouts of Dask arrays, trajectories to Zarr, a Dask cluster for
the CLI's ensemble jobs.

- :func:`integrate_dask` (what :func:`~poisson_rs.integrate` calls for a ``dask.array.Array``):
  a lazy rollout, one Rust rollout per chunk of initial states, in whichever process or worker
  computes that chunk. Trajectories are independent in the core, so the result is bit-identical
  to the in-process call whatever the chunking and the number of workers.
- :func:`to_zarr`: an ensemble written chunk by chunk to a Zarr store, never whole in memory.
- :func:`scheduler_client` and :func:`run_all`: a ``distributed`` client for ``--scheduler``
  (``local``: a LocalCluster sized to the machine; else a scheduler address) and independent jobs
  run on it in order, with a progress bar following the futures.

Dask, ``distributed`` and Zarr are optional (``pip install poisson_rs[distributed]``): this module
imports them only inside the functions that need them, and ``integrate`` imports it only when
given a dask array.
"""

from __future__ import annotations

import os
import shutil
import socket
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .files import check_output_path, temporary_name
from .protocols import Stepper
from .rollout import (  # noqa: F401 (integrate_dask and is_dask_array are imported from here)
    _EXTRA,
    INFO_FIELDS,
    RolloutInfo,
    integrate,
    integrate_dask,
    is_dask_array,
)
from .untrusted import parsing

if TYPE_CHECKING:
    from distributed import Client

#: Trajectories per chunk when :func:`to_zarr` is given a NumPy array.
DEFAULT_CHUNK = 10_000
#: Seconds to wait for a scheduler address to answer before giving up.
CONNECT_TIMEOUT = 10.0


def to_zarr(
    stepper: Stepper,
    mu0: Any,
    h: float,
    n_steps: int,
    path: str | os.PathLike[str],
    *,
    every: int = 1,
    chunk: int | None = None,
    info: bool = True,
    strict: bool = True,
    compute_kwargs: Mapping[str, Any] | None = None,
) -> Path:
    """Writes an ensemble's rollout straight to a new Zarr store at ``path``, chunk by chunk.

    mu0: (n, dim) states, a NumPy array-like (cut into chunks of ``chunk`` trajectories,
    default :data:`DEFAULT_CHUNK`) or a dask array (rechunked to ``chunk`` when given, or when
    its chunks are irregular). The store holds ``trajectories`` (n, n_steps // every + 1, dim)
    float64, chunked (chunk, all records, dim), and with ``info`` one (n,) array per
    :class:`~poisson_rs.integrators.RolloutInfo` field under ``info/``; its attributes record
    h, n_steps, every, the stepper, the system's ``to_dict()`` (:func:`zarr_system` rebuilds
    it) and ``complete``. The store is written under a temporary name beside ``path`` and
    renamed when complete, so an interrupted run leaves nothing at ``path``. Read it back with
    ``zarr.open_group(path)`` or ``dask.array.from_zarr(path, component="trajectories")``.

    Memory: each chunk is computed, written and released, so the writing process holds about
    (chunks in flight) × chunk × records × dim × 8 bytes, whatever n. Computes with the current
    Dask scheduler (a ``distributed.Client`` when one is active, else threads); on a cluster
    ``path`` must be a location every worker can write. ``path`` must be new (ValueError
    otherwise; see :func:`~poisson_rs.files.check_output_path`). Returns the path.
    """
    import dask
    import dask.array as da
    import zarr

    path = check_output_path(path, kind="dir")
    if os.path.lexists(path):
        raise ValueError(f"output {path} exists; to_zarr writes a new path only")
    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1):
        raise ValueError(f"chunk must be an integer >= 1, got {chunk!r}")
    if not is_dask_array(mu0):
        from .rollout import _as_states

        dim = int(getattr(stepper, "dim", 3))
        states, _ = _as_states(mu0, dim=dim)
        mu0 = da.from_array(states, chunks=(chunk or DEFAULT_CHUNK, dim))
    elif chunk is not None:
        mu0 = mu0.rechunk({0: chunk})
    elif len(set(mu0.chunks[0][:-1])) > 1 or mu0.chunks[0][-1] > mu0.chunks[0][0]:
        mu0 = mu0.rechunk({0: max(mu0.chunks[0])})  # Zarr needs regular chunks
    traj, rollout_info = integrate_dask(
        stepper, mu0, h, n_steps, every=every, return_info=True, on_failure="ignore", strict=strict
    )
    # Written under a temporary name beside the target and renamed when complete: an interrupt
    # (Ctrl-C, a killed worker, a full disk) leaves no partial store at `path`, so a re-run
    # works. The temporary store is removed on any failure; one left by a killed process is a
    # hidden folder that nothing reads.
    tmp = temporary_name(path, "zarr-partial")
    try:
        group = zarr.open_group(str(tmp), mode="w-")
        group.attrs.update(_store_attributes(stepper, h, n_steps, every, complete=False))
        arrays = {"trajectories": traj}
        if info:
            arrays.update({f"info/{k}": getattr(rollout_info, k) for k in INFO_FIELDS})
        stores = [
            da.to_zarr(a, str(tmp), component=name, compute=False, mode="a")
            for name, a in arrays.items()
        ]
        # One compute: each chunk's rollout runs once and feeds all its arrays.
        dask.compute(*stores, **dict(compute_kwargs or {}))
        group.attrs["complete"] = True
        # Checked again right before the rename: the path may have appeared meanwhile (and
        # os.rename would replace an empty folder there).
        if os.path.lexists(path):
            raise ValueError(f"output {path} appeared while the ensemble was computed")
        os.rename(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def _store_attributes(
    stepper: Stepper, h: float, n_steps: int, every: int, *, complete: bool
) -> dict[str, Any]:
    """What a store records: the run (h, n_steps, every), the stepper, the system as its
    ``to_dict()`` (:func:`zarr_system` rebuilds it) and whether the store is complete."""
    system = getattr(stepper, "system", None)
    return {
        "h": float(h),
        "n_steps": int(n_steps),
        "every": int(every),
        "stepper": repr(stepper),
        "system": system.to_dict() if callable(getattr(system, "to_dict", None)) else None,  # type: ignore[union-attr]
        "complete": complete,
    }


def zarr_system(path: str | os.PathLike[str]) -> Any:
    """The system (any structure's) an ensemble written by :func:`to_zarr` integrates, rebuilt from
    the store's attributes. ValueError (:class:`~poisson_rs.untrusted.InputError`) naming the
    store when it is incomplete or records no valid system."""
    import zarr

    source = f"Zarr store {path}"
    with parsing(source):
        attrs = dict(zarr.open_group(str(path), mode="r").attrs)
    with parsing(source, "complete"):
        if attrs.get("complete") is not True:
            raise ValueError("the store is not complete (its writer was interrupted)")
    with parsing(source, "system"):
        spec = attrs.get("system")
        if spec is None:
            raise ValueError("the store records no system")
        from .structures import system_from_dict

        if not isinstance(spec, Mapping):
            raise ValueError(f"the store's system must be a table, got {type(spec).__name__}")
        return system_from_dict(spec)


def connect(address: str, *, timeout: float = CONNECT_TIMEOUT) -> Client:
    """A ``distributed.Client`` on the scheduler at ``address`` (e.g. "tcp://10.0.0.1:8786").

    Raises ValueError naming the address when it is malformed or does not answer within
    ``timeout`` seconds, and when ``distributed`` is not installed.
    """
    try:
        from distributed import Client
        from distributed.comm.addressing import parse_address, parse_host_port
    except ImportError:
        raise ValueError(f"a Dask scheduler needs the distributed extra: {_EXTRA}") from None
    try:
        scheme, location = parse_address(address)
        host, port = parse_host_port(location) if scheme in ("tcp", "tls") else (None, None)
    except (ValueError, TypeError) as e:
        raise ValueError(
            f"{address!r} is not a Dask scheduler address such as tcp://host:8786 ({e})"
        ) from None
    if host is not None:
        # A plain socket first: a Client that fails to connect lingers and complains at exit.
        try:
            socket.create_connection((host, port), timeout=timeout).close()
        except OSError as e:
            raise ValueError(
                f"cannot reach a Dask scheduler at {address!r} within {timeout:g} s ({e})"
            ) from None
    try:
        return Client(address, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError, ValueError, TypeError) as e:
        raise ValueError(
            f"cannot reach a Dask scheduler at {address!r} within {timeout:g} s "
            f"({type(e).__name__}: {e})"
        ) from None


@contextmanager
def scheduler_client(
    scheduler: str | None, *, timeout: float = CONNECT_TIMEOUT
) -> Iterator[Client | None]:
    """The client of a CLI's ``--scheduler``: None for None (serial, in process); for "local" a
    LocalCluster of one single-threaded worker process per core (closed on exit), else
    :func:`connect` to that address. Worker processes of a local cluster inherit this process's
    environment (RAYON_NUM_THREADS included)."""
    if scheduler is None:
        yield None
        return
    if scheduler != "local":
        client = connect(scheduler, timeout=timeout)
        try:
            yield client
        finally:
            client.close()
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ValueError(f"--scheduler local needs the distributed extra: {_EXTRA}") from None
    with (
        LocalCluster(
            n_workers=os.cpu_count() or 1,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
        ) as cluster,
        Client(cluster, set_as_default=False) as client,
    ):
        yield client


def run_all(
    client: Client,
    fn: Callable[..., Any],
    jobs: Sequence[tuple[Sequence[Any], Mapping[str, Any]]],
    *,
    desc: str = "jobs",
    progress: bool = True,
) -> list[Any]:
    """``[fn(*args, **kwargs) for args, kwargs in jobs]``, each call a future on ``client``;
    results in the order of ``jobs``. A tqdm bar (on stderr) follows the futures as they finish.
    The first job to raise re-raises here; a worker lost mid-job has its job rerun elsewhere."""
    from distributed import as_completed
    from tqdm import tqdm

    futures = [client.submit(fn, *args, pure=False, **kwargs) for args, kwargs in jobs]
    try:
        with (
            client.as_current(),  # as_completed follows the current client's futures
            tqdm(total=len(futures), desc=desc, disable=not progress, file=sys.stderr) as bar,
        ):
            for _ in as_completed(futures):
                bar.update(1)
        return list(client.gather(futures))
    finally:
        for f in futures:
            f.release()
