"""pr.learn's data files (learn/data.py): untrusted input, read only as regular files of bounded
size whose arrays declare a bounded size before anything is decompressed."""

from __future__ import annotations

import io
import json
import os
import threading
import zipfile

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs.learn import data as learn_data
from poisson_rs.learn import load_trajectories

zarr = pytest.importorskip("zarr")

BODY = pr.RigidBody((2.0, 1.0, 2.0 / 3.0))


def _records(n_traj: int = 3, records: int = 6) -> np.ndarray:
    rng = np.random.default_rng(0)
    y0 = rng.normal(size=(n_traj, 3))
    y0 /= np.linalg.norm(y0, axis=1, keepdims=True)
    return pr.reference_solution(BODY, y0, 0.1 * np.arange(records))


def _csv_bytes(traj: np.ndarray) -> bytes:
    rows = ["traj,m1,m2,m3"] + [
        ",".join([str(i), *map(repr, r.tolist())]) for i, t in enumerate(traj) for r in t
    ]
    return ("\n".join(rows) + "\n").encode()


class _FifoWriter:
    """A writer on a FIFO that feeds ``payload`` to every reader that opens it (a reader that
    opens the FIFO, even twice, gets valid data: code that reads FIFOs fails the test by
    accepting it, instead of hanging). ``close`` stops it."""

    def __init__(self, path, payload: bytes) -> None:
        self.path = path
        self.stop = False
        os.mkfifo(path)
        self.thread = threading.Thread(target=self._serve, args=(payload,), daemon=True)
        self.thread.start()

    def _serve(self, payload: bytes) -> None:
        while not self.stop:
            try:
                fd = os.open(self.path, os.O_WRONLY)  # blocks until a reader opens
            except OSError:
                return
            try:
                if not self.stop:
                    os.write(fd, payload)
            except OSError:  # the reader closed early (EPIPE): what a refusal does
                pass
            finally:
                os.close(fd)

    def close(self) -> None:
        self.stop = True
        while self.thread.is_alive():
            fd = os.open(self.path, os.O_RDONLY | os.O_NONBLOCK)  # unblocks a waiting writer
            self.thread.join(0.5)
            os.close(fd)


@pytest.fixture
def fifo(tmp_path):
    writers = []

    def make(name: str, payload: bytes):
        w = _FifoWriter(tmp_path / name, payload)
        writers.append(w)
        return tmp_path / name

    yield make
    for w in writers:
        w.close()


def _npz_bytes(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


# --- files that are not regular ------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_a_fifo_as_the_data_file_is_refused(fifo, suffix) -> None:
    traj = _records()
    payload = _csv_bytes(traj) if suffix == ".csv" else _npz_bytes(trajectories=traj)
    path = fifo(f"d{suffix}", payload)
    with pytest.raises(ValueError, match=r"data file .* is a FIFO, not a regular file"):
        load_trajectories(path)


def test_a_link_to_dev_zero_is_refused(tmp_path) -> None:
    if not os.path.exists("/dev/zero"):
        pytest.skip("no /dev/zero")
    for name in ("z.csv", "z.npz"):
        os.symlink("/dev/zero", tmp_path / name)
        with pytest.raises(ValueError, match="is a character device, not a regular file"):
            load_trajectories(tmp_path / name)


def test_a_fifo_chunk_inside_a_zarr_store_is_refused(tmp_path, fifo) -> None:
    store = tmp_path / "s.zarr"
    group = zarr.open_group(str(store), mode="w", zarr_format=2)
    group.create_array("trajectories", data=_records(), chunks=(1, 6, 3))
    group.attrs["complete"] = True
    chunk = store / "trajectories" / "1.0.0"
    payload = chunk.read_bytes()
    chunk.unlink()
    fifo("s.zarr/trajectories/1.0.0", payload)
    with pytest.raises(ValueError, match=r"trajectories/1\.0\.0 is a FIFO, not a regular file"):
        load_trajectories(store)


def test_a_fifo_as_the_system_file_is_refused_before_the_fit(tmp_path, fifo, monkeypatch) -> None:
    import argparse

    from poisson_rs.learn import api, cli

    monkeypatch.setattr(api, "learn", _never)
    known = pr.LiePoissonSystem(pr.LieAlgebra.so3(), pr.Polynomial({(2, 0, 0): 0.5}))
    np.savez(tmp_path / "d.npz", trajectories=_records())
    system = fifo("known.json", json.dumps(known.to_dict()).encode())
    parser = argparse.ArgumentParser()
    cli.add_parser(parser.add_subparsers())
    out = str(tmp_path / "m.safetensors")
    argv = ["learn", str(tmp_path / "d.npz"), "--h", "0.1", "--out", out, "--mode", "hj+data"]
    args = parser.parse_args([*argv, "--system", str(system)])
    with pytest.raises(ValueError, match=r"--system .*is a FIFO, not a regular file"):
        args.func(args)


def _never(*args, **kwargs):
    raise AssertionError("the fit ran")


# --- decompression bombs and lying sizes --------------------------------------------------------


def test_a_deflate_bomb_npz_is_refused_before_decompressing(tmp_path, monkeypatch) -> None:
    """A real bomb: 64 MiB of deflated zeros (a file of ~64 KiB) under a cap of 16 MiB. The
    declared sizes refuse it; no array is ever read."""
    monkeypatch.setattr(learn_data, "MAX_DATA_BYTES", 16 << 20)
    records = (64 << 20) // (20 * 3 * 8)
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f8", "fortran_order": False, "shape": (records, 20, 3)}
    )
    path = tmp_path / "bomb.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        with zf.open("trajectories.npy", "w", force_zip64=True) as fh:
            fh.write(header.getvalue())
            zeros = bytes(1 << 20)
            for _ in range(64):
                fh.write(zeros)
    assert path.stat().st_size < 1 << 20
    monkeypatch.setattr(np.lib.format, "read_array", _never)
    with pytest.raises(ValueError, match="decompressed, more than the 16777216 allowed"):
        load_trajectories(path)


def test_an_npz_whose_header_declares_a_huge_shape_is_refused(tmp_path, monkeypatch) -> None:
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f8", "fortran_order": False, "shape": (20_000_000, 20, 3)}
    )
    path = tmp_path / "lie.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("trajectories.npy", header.getvalue() + bytes(480))
    monkeypatch.setattr(np.lib.format, "read_array", _never)
    with pytest.raises(ValueError, match=r"declares shape \(20000000, 20, 3\)"):
        load_trajectories(path)


def test_a_zarr_store_declaring_a_huge_shape_is_refused(tmp_path, monkeypatch) -> None:
    store = tmp_path / "s.zarr"
    group = zarr.open_group(str(store), mode="w", zarr_format=2)
    group.create_array("trajectories", data=_records(), chunks=(1, 6, 3))
    group.attrs["complete"] = True
    meta_path = store / "trajectories" / ".zarray"
    meta = json.loads(meta_path.read_text())
    meta["shape"] = [20_000_000, 20, 3]
    meta_path.write_text(json.dumps(meta))
    monkeypatch.setattr(zarr.Array, "__getitem__", _never)
    with pytest.raises(ValueError, match=r"field trajectories: declares shape \(20000000, 20, 3\)"):
        load_trajectories(store)


def test_an_incomplete_zarr_store_is_refused(tmp_path) -> None:
    """An interrupted writer leaves complete = false and chunks missing (read as 0.0)."""
    store = tmp_path / "s.zarr"
    group = zarr.open_group(str(store), mode="w", zarr_format=2)
    group.create_array("trajectories", data=_records(), chunks=(1, 6, 3))
    group.attrs["complete"] = False
    (store / "trajectories" / "2.0.0").unlink()
    with pytest.raises(ValueError, match="field complete: the store is not marked complete"):
        load_trajectories(store)
    # The same store, complete, reads back (the refusal is the flag's, not the format's).
    store2 = tmp_path / "t.zarr"
    good = zarr.open_group(str(store2), mode="w", zarr_format=2)
    good.create_array("trajectories", data=_records(), chunks=(1, 6, 3))
    good.attrs["complete"] = True
    assert np.array_equal(np.stack(load_trajectories(store2)), _records())


# --- empty files ---------------------------------------------------------------------------------


def test_empty_files_get_one_clear_error(tmp_path) -> None:
    (tmp_path / "h.csv").write_text("traj,m1,m2,m3\n")
    with pytest.raises(ValueError, match=r"h\.csv, field csv rows: holds no records"):
        load_trajectories(tmp_path / "h.csv")
    np.savez(tmp_path / "e.npz")
    with pytest.raises(ValueError, match=r"e\.npz, field npz arrays: holds no arrays"):
        load_trajectories(tmp_path / "e.npz")
