"""Ensembles on Dask: picklable steppers, lazy rollouts of dask arrays bit-identical to the
in-process ones on a real two-process LocalCluster, a worker lost mid-job, Zarr output in
bounded memory, ``--scheduler`` for the CLI's ensemble jobs."""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
import textwrap
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import poisson_rs as pr
from poisson_rs import ensembles

da = pytest.importorskip("dask.array")
distributed = pytest.importorskip("distributed")
pytest.importorskip("zarr")

from conftest import RandomModel, random_states  # noqa: E402

RIGID = pr.RigidBody()
TOP = pr.HeavyTop()
PYTHON_DIR = Path(pr.__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def client() -> Iterator[Any]:
    """Two single-threaded worker processes (each rollout on one rayon thread)."""
    with (
        distributed.LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            env={"RAYON_NUM_THREADS": "1"},
        ) as cluster,
        distributed.Client(cluster, set_as_default=False) as c,
    ):
        yield c


def top_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """n heavy-top states (M, Γ) with |Γ| = 1: (n, 6)."""
    m = rng.normal(size=(n, 3))
    g = rng.normal(size=(n, 3))
    return np.concatenate([m, g / np.linalg.norm(g, axis=1, keepdims=True)], axis=1)


def in_process(stepper: Any, mu0: np.ndarray, h: float, n: int, every: int = 1) -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return pr.integrate(stepper, mu0, h, n, every=every, return_info=True, on_failure="ignore")


def assert_same(a: tuple[np.ndarray, Any], b: tuple[np.ndarray, Any]) -> None:
    """Bit-identical trajectories and info."""
    (ta, ia), (tb, ib) = a, b
    assert ta.shape == tb.shape and ta.dtype == tb.dtype
    assert ta.tobytes() == tb.tobytes()
    for k in ensembles.INFO_FIELDS:
        x, y = np.asarray(getattr(ia, k)), np.asarray(getattr(ib, k))
        assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), k


def on_cluster(
    client: Any, stepper: Any, mu0: np.ndarray, h: float, n: int, every: int, chunk: int
) -> tuple[np.ndarray, Any]:
    """The rollout of ``mu0`` in chunks of ``chunk`` states, computed on the cluster: the
    trajectories and a RolloutInfo, as :func:`in_process` returns them."""
    traj, info = pr.integrate(
        stepper, da.from_array(mu0, chunks=(chunk, -1)), h, n, every=every, return_info=True
    )
    fields = [getattr(info, k) for k in ensembles.INFO_FIELDS]
    out = client.gather(client.compute([traj, *fields]))
    return out[0], pr.RolloutInfo(**dict(zip(ensembles.INFO_FIELDS, out[1:], strict=True)))


# --- pickling ---------------------------------------------------------------------------------


def every_stepper(random_model: RandomModel) -> dict[str, Any]:
    model = random_model(3, widths=(8, 8))
    assert model.path is not None
    out: dict[str, Any] = {
        "learned from file": model,
        "learned from bytes": pr.LearnedIntegrator(model.path.read_bytes(), tol=1e-10),
        "shipped default, full Newton": pr.load_model(max_iter=30, newton="full"),
        "taylor rigid body cayley": pr.taylor_integrator(RIGID, 5, "cayley"),
        "taylor rigid body exp": pr.taylor_integrator(RIGID, 3, "exp"),
        "taylor heavy top": pr.taylor_integrator(TOP, 3),
    }
    for system in (RIGID, TOP):
        for name in pr.classical_methods(system):
            out[f"classical {name} {type(system).__name__}"] = pr.classical(system, name, tol=1e-9)
    return out


def test_every_stepper_pickles_to_identical_rollouts(random_model: RandomModel) -> None:
    rng = np.random.default_rng(0)
    for label, stepper in every_stepper(random_model).items():
        copy = pickle.loads(pickle.dumps(stepper))
        assert type(copy) is type(stepper), label
        assert repr(copy) == repr(stepper), label
        for attr in ("tol", "max_iter", "newton", "name"):
            assert getattr(copy, attr, None) == getattr(stepper, attr, None), (label, attr)
        mu0 = top_states(rng, 5) if stepper.dim == 6 else random_states(rng, 5, 1.0, 2.5)
        n = 4 if "dop853" in label else 20
        assert_same(in_process(copy, mu0, 0.05, n), in_process(stepper, mu0, 0.05, n))


def test_file_model_pickles_its_bytes_not_its_path(
    random_model: RandomModel, tmp_path: Path
) -> None:
    src = random_model(4, widths=(4,)).path
    assert src is not None
    path = tmp_path / "moved.safetensors"
    path.write_bytes(src.read_bytes())
    model = pr.load_model(path)
    data = pickle.dumps(model)
    assert str(path).encode() not in data
    path.write_bytes(b"overwritten")  # the pickle does not depend on the file any more
    copy = pickle.loads(data)
    assert copy.path is None and copy.name == model.name
    mu0 = random_states(np.random.default_rng(1), 3)
    assert_same(in_process(copy, mu0, 0.1, 10), in_process(model, mu0, 0.1, 10))


def test_systems_pickle() -> None:
    algebra = pr.LieAlgebra.so3()
    for system in (RIGID, TOP, pr.RigidBody((1.0, 2.0, 3.0)), TOP.algebra, algebra):
        copy = pickle.loads(pickle.dumps(system))
        assert type(copy) is type(system) and repr(copy) == repr(system)
    generic = pr.LiePoissonSystem(TOP.algebra, TOP.polynomial)
    copy = pickle.loads(pickle.dumps(generic))
    assert copy.to_dict() == generic.to_dict()
    assert pickle.loads(pickle.dumps(TOP.polynomial)).to_dict() == TOP.polynomial.to_dict()


# --- integrate on dask arrays -----------------------------------------------------------------


def test_integrate_on_dask_is_lazy_and_chunked_like_its_input() -> None:
    mu0 = random_states(np.random.default_rng(2), 10)
    traj, info = pr.integrate(
        pr.load_model(), da.from_array(mu0, chunks=(4, 3)), 0.1, 20, every=5, return_info=True
    )
    assert isinstance(traj, da.Array) and isinstance(info.converged, da.Array)
    assert traj.shape == (10, 5, 3) and traj.chunks == ((4, 4, 2), (5,), (3,))
    assert info.max_residual.chunks == ((4, 4, 2),)
    single = pr.integrate(pr.load_model(), da.from_array(mu0[0]), 0.1, 4)
    assert single.shape == (5, 3)
    assert (
        single.compute(scheduler="sync").tobytes()
        == in_process(pr.load_model(), mu0[0], 0.1, 4)[0].tobytes()
    )
    with pytest.raises(ValueError, match="h_max"):
        pr.integrate(pr.load_model(), da.from_array(mu0), 0.5, 10)
    with pytest.raises(ValueError, match=r"shape \(3,\) or \(n, 3\)"):
        pr.integrate(pr.load_model(), da.zeros((4, 2)), 0.1, 10)
    with pytest.raises(ValueError, match="NaN"):
        pr.integrate(pr.load_model(), da.full((4, 3), np.nan), 0.1, 10).compute(scheduler="sync")


def test_integrate_imports_no_dask() -> None:
    code = (
        "import sys, poisson_rs as pr; pr.integrate(pr.load_model(), [1.0, 1.0, 2.0], 0.1, 3); "
        "sys.exit(any(m.split('.')[0] in ('dask', 'distributed', 'zarr') for m in sys.modules))"
    )
    env = {**os.environ, "PYTHONPATH": str(PYTHON_DIR)}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=60)


@pytest.mark.parametrize("chunk", [7, 40])
@pytest.mark.parametrize("kind", ["learned", "taylor heavy top", "classical"])
def test_cluster_rollouts_bit_identical(client: Any, kind: str, chunk: int) -> None:
    rng = np.random.default_rng(5)
    if kind == "learned":
        stepper, mu0, h, n, every = pr.load_model(), random_states(rng, 100, 1.0, 4.0), 0.1, 30, 3
    elif kind == "taylor heavy top":
        stepper, mu0, h, n, every = pr.taylor_integrator(TOP, 3), top_states(rng, 60), 0.05, 20, 1
    else:
        stepper, mu0 = pr.classical(RIGID, "midpoint"), random_states(rng, 100)
        h, n, every = 0.1, 40, 4
    assert_same(
        on_cluster(client, stepper, mu0, h, n, every, chunk), in_process(stepper, mu0, h, n, every)
    )


def nambu_steppers() -> list[Any]:
    from poisson_rs.structures.polynomial import (
        PolynomialBivector,
        PolynomialPoissonSystem,
        RealizationTaylorIntegrator,
        VectorFieldIntegrator,
    )

    system = PolynomialPoissonSystem(
        PolynomialBivector.nambu("x1**2/2 + x2**2/2 + x3**2/2 + x1**3/3"), "x1**2/2 + x2**2/3"
    )
    return [
        RealizationTaylorIntegrator(system, 3),
        RealizationTaylorIntegrator(system, 1, 2, tol=1e-12),
        VectorFieldIntegrator(system, "midpoint", max_iter=60),
    ]


def test_polynomial_bivector_steppers_pickle_to_identical_rollouts() -> None:
    """The NumPy steppers of a polynomial bivector hold lambdified sympy; they pickle as their
    sympy text and options and roll out the same bits after the round trip."""
    mu0 = np.random.default_rng(8).uniform(-0.6, 0.6, (5, 3))
    for stepper in nambu_steppers():
        copy = pickle.loads(pickle.dumps(stepper))
        assert (copy.name, copy.tol, copy.max_iter) == (stepper.name, stepper.tol, stepper.max_iter)
        assert_same(in_process(copy, mu0, 0.1, 6), in_process(stepper, mu0, 0.1, 6))


def test_polynomial_bivector_on_cluster_bit_identical(client: Any) -> None:
    stepper = nambu_steppers()[0]
    mu0 = np.random.default_rng(9).uniform(-0.6, 0.6, (30, 3))
    assert_same(
        on_cluster(client, stepper, mu0, 0.1, 8, 2, 11), in_process(stepper, mu0, 0.1, 8, 2)
    )


def lotka_volterra_steppers() -> dict[str, Any]:
    pnn = pr.lotka_volterra([[0.0, 1.0], [-1.0, 0.0]], [1.0, 2.0])
    return {
        "taylor": pr.log_canonical_taylor(pnn, 5),
        "learned": pr.load_model("lotka_volterra_h01"),
        "log_splitting4": pr.log_canonical_classical(pnn, "log_splitting4"),
        "rk4": pr.log_canonical_classical(pnn, "rk4"),
    }


def lotka_volterra_states(seed: int, n: int) -> np.ndarray:
    """States within a log distance of 0.4 of PNN's equilibrium (1, 2)."""
    return np.exp(np.random.default_rng(seed).uniform(-0.4, 0.4, (n, 2))) * [1.0, 2.0]


def test_lotka_volterra_steppers_pickle_to_identical_rollouts() -> None:
    x0 = lotka_volterra_states(10, 5)
    for label, stepper in lotka_volterra_steppers().items():
        copy = pickle.loads(pickle.dumps(stepper))
        assert type(copy) is type(stepper) and repr(copy) == repr(stepper), label
        assert_same(in_process(copy, x0, 0.1, 20), in_process(stepper, x0, 0.1, 20))


@pytest.mark.parametrize("kind", ["taylor", "learned", "log_splitting4"])
def test_lotka_volterra_on_cluster_bit_identical(client: Any, kind: str) -> None:
    stepper = lotka_volterra_steppers()[kind]
    x0 = lotka_volterra_states(11, 50)
    assert_same(
        on_cluster(client, stepper, x0, 0.1, 30, 3, 13), in_process(stepper, x0, 0.1, 30, 3)
    )


class DieOnce:
    """A stepper whose first rollout of some states, anywhere, kills the process running it (the
    marker file says it happened); later rollouts are the wrapped stepper's."""

    def __init__(self, stepper: Any, marker: Path) -> None:
        self.stepper, self.marker = stepper, marker

    @property
    def dim(self) -> int:
        return int(self.stepper.dim)

    def rollout(self, mu0: np.ndarray, h: float, n_steps: int, every: int) -> Any:
        if not len(mu0):  # integrate's argument check, in the calling process
            return self.stepper.rollout(mu0, h, n_steps, every)
        try:
            os.close(os.open(self.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:
            return self.stepper.rollout(mu0, h, n_steps, every)
        os._exit(1)  # the worker process dies mid-task


def test_worker_killed_mid_job_leaves_result_intact(client: Any, tmp_path: Path) -> None:
    marker = tmp_path / "died"
    stepper = DieOnce(pr.taylor_integrator(RIGID, 3), marker)
    mu0 = random_states(np.random.default_rng(6), 64)
    traj, info = pr.integrate(
        stepper, da.from_array(mu0, chunks=(16, 3)), 0.1, 50, return_info=True
    )
    out = client.gather(client.compute([traj, info.converged]))
    assert marker.exists()  # a worker did die
    expect = in_process(stepper, mu0, 0.1, 50)
    assert out[0].tobytes() == expect[0].tobytes()
    assert out[1].all()


# --- Zarr -------------------------------------------------------------------------------------

ZARR_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import numpy as np, poisson_rs as pr
    from poisson_rs import ensembles

    def status(key):  # kB in /proc/self/status
        line = next(x for x in open("/proc/self/status") if x.startswith(key + ":"))
        return int(line.split()[1]) * 1024

    path, n, steps, chunk = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    rk4 = pr.classical(pr.RigidBody(), "rk4")
    mu0 = np.random.default_rng(7).normal(size=(n, 3))
    ensembles.to_zarr(rk4, mu0[:8], 0.01, 2, path + ".warm", chunk=4)  # imports, pools
    # getrusage's ru_maxrss would carry the parent's peak across fork and exec: the kernel's
    # high-water mark VmHWM, reset to the current RSS here, measures this write alone.
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    before = status("VmRSS")
    ensembles.to_zarr(rk4, mu0, 0.01, steps, path, chunk=chunk, compute_kwargs={"num_workers": 2})
    print(json.dumps({"growth_bytes": status("VmHWM") - before}))
    """
)


@pytest.mark.skipif(
    not os.access("/proc/self/clear_refs", os.W_OK), reason="needs Linux's peak-RSS reset"
)
def test_to_zarr_writes_a_large_ensemble_in_bounded_memory(tmp_path: Path) -> None:
    import zarr

    n, steps, chunk = 100_000, 100, 2_000
    full = n * (steps + 1) * 3 * 8  # 242 MB of float64 trajectories
    path = tmp_path / "ensemble.zarr"
    env = {**os.environ, "PYTHONPATH": str(PYTHON_DIR)}
    run = subprocess.run(
        [sys.executable, "-c", ZARR_SCRIPT, str(path), str(n), str(steps), str(chunk)],
        check=True,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    growth = json.loads(run.stdout.strip().splitlines()[-1])["growth_bytes"]
    # The writer's peak RSS grows by a few chunks (4.8 MB each), not by the output (~36 MB
    # measured, of which Zarr's and the threads' buffers).
    assert 0 < growth < full / 4, (growth, full)
    group = zarr.open_group(str(path), mode="r")
    assert group["trajectories"].shape == (n, steps + 1, 3)
    assert group.attrs["n_steps"] == steps
    mu0 = np.random.default_rng(7).normal(size=(n, 3))
    rows = slice(51_990, 52_010)  # across a chunk boundary
    expect, info = in_process(pr.classical(RIGID, "rk4"), mu0[rows], 0.01, steps)
    assert group["trajectories"][rows].tobytes() == expect.tobytes()
    assert np.array_equal(group["info/converged"][rows], info.converged)


def test_to_zarr_writes_only_new_paths(tmp_path: Path) -> None:
    (tmp_path / "exists").mkdir()
    rk4 = pr.classical(RIGID, "rk4")
    with pytest.raises(ValueError, match="new path"):
        ensembles.to_zarr(rk4, np.ones((2, 3)), 0.1, 2, tmp_path / "exists")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="not a directory"):
        ensembles.to_zarr(rk4, np.ones((2, 3)), 0.1, 2, tmp_path / "file")


# --- the CLI's ensemble jobs ------------------------------------------------------------------


def test_bad_scheduler_address_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from poisson_rs.cli import main

    with pytest.raises(ValueError, match=r"tcp://127\.0\.0\.1:1"):
        ensembles.connect("tcp://127.0.0.1:1", timeout=2)
    with pytest.raises(ValueError, match="not a Dask scheduler address"):
        ensembles.connect("no:such:address")
    args = ["stability", "--quick", "--out", str(tmp_path / "s"), "--no-progress"]
    assert main([*args, "--scheduler", "tcp://127.0.0.1:1"]) == 2
    err = capsys.readouterr().err
    assert "cannot reach a Dask scheduler at 'tcp://127.0.0.1:1'" in err
    assert "Traceback" not in err


def test_stability_map_on_cluster_same_rows(client: Any) -> None:
    from poisson_rs.studies.stability import stability_map

    methods = {
        "learned": pr.load_model,
        "taylor3": lambda: pr.taylor_integrator(RIGID, 3),
        "rk4": lambda: pr.classical(RIGID, "rk4"),
    }
    kw: dict[str, Any] = {"step_sizes": (0.1, 1.0), "radii": (1.0, 6.0), "horizon": 5.0}
    serial = stability_map(methods=methods, **kw)
    spread = stability_map(methods=methods, client=client, **kw)
    assert repr(spread) == repr(serial)


def test_work_precision_points_on_cluster(client: Any) -> None:
    from poisson_rs.studies.workprecision import Method, paper_scene, sweep

    methods = [
        Method("rk4", "classical", pr.classical(RIGID, "rk4")),
        Method("taylor3", "taylor", pr.taylor_integrator(RIGID, 3)),
    ]
    scene = paper_scene()
    serial = sweep([scene], methods, (50, 100), repeats=False)
    spread = sweep([scene], methods, (50, 100), repeats=False, client=client)
    timing = ("seconds_per_traj", "cpu_seconds_per_traj", "repeats")
    strip = [{k: v for k, v in r.items() if k not in timing} for r in (*serial, *spread)]
    assert len(serial) == 4 and repr(strip[4:]) == repr(strip[:4])


def test_sweep_trainings_as_futures_same_numbers(client: Any) -> None:
    from poisson_rs.studies.sweep import run_sweep

    kw: dict[str, Any] = {
        "architectures": ((4,), (4, 4)),
        "seeds": (0,),
        "iterations": 10,
        "batch": 128,
        "shipped": (),
        "baselines": False,
        "speed_seconds": 0.01,
    }
    serial = run_sweep(**kw)
    spread = run_sweep(client=client, **kw)
    timing = ("train_seconds", "steps_per_s")
    assert [{k: v for k, v in r.items() if k not in timing} for r in spread] == [
        {k: v for k, v in r.items() if k not in timing} for r in serial
    ]
