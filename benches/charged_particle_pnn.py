"""PNN's charged particle (their LFData) on the package's charged-particle structure.

B = |x|, A = |x|/3 (−x₂, x₁), H = |v|²/2 + 1/(100|x|) (``scenes/charged_particle_pnn.toml``),
their one state (x, v) = (0.5, 1, 1, 0.5) and h = 0.1: 1500 training records by
``pr.reference_solution`` (DOP853, rtol = atol = 1e-13), tested from the exact state at the end
of the training span on the next 300 steps and on 10× that (3000); errors relative, max over
the test times of |z(t) − z_exact(t)| / |z_exact(t)|; the energy drift the largest relative
|H(z_t) − H(z_0)| / |H(z_0)| along 10⁴ steps from the test start. Rows: the true system through
Taylor-HJ by jets (m = 3, 5) and RK4; ``pr.learn(records, 0.1, structure=<the system>)`` (H
learned from the structure's polynomial family, B and A given); ``pr.learn(records, 0.1,
structure="discover")``, given ``--discover-seconds`` (default 600) in a child process and
recorded as cut off past that. One pinned core, one torch thread::

    PYTHONPATH=python taskset -c 0 .venv/bin/python benches/charged_particle_pnn.py \\
        --out docs/learning/charged_particle_pnn.json

``--pnn CHECKOUT --pnn-iterations N``: PNN itself (their ``main.py`` ``LF()``: INN(4, 2, 10, 3,
50, sigmoid, volume preserving) + GSympNet(4, 10, 50, sigmoid), 30,020 parameters, Adam lr 1e-3,
full batch, float32, best checkpoint by their test loss) on their own ``LFData`` records, N of
their 2M iterations (about 70 ms an iteration on one core here: all of them would take ~40 h),
scored as the rows above; ``--only-pnn`` runs that row alone and keeps the others of ``--out``;
without ``--pnn`` an existing PNN row of ``--out`` is kept; ``--only-discover`` runs the
discovery row alone and keeps the others, ``--sigma S`` with it on records with relative noise S.
The checkout is taken at bench time, never vendored (see ``benches/structure_protocols.py``)::

    PYTHONPATH=python taskset -c 1 .venv/bin/python benches/charged_particle_pnn.py \\
        --pnn /tmp/peers/pnn --pnn-iterations 20000 --only-pnn --peer-site /tmp/peer-site
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

import poisson_rs as pr
from poisson_rs.scenes import load_scene

ROOT = Path(__file__).resolve().parents[1]
H, TRAIN_STEPS, TEST_STEPS, DRIFT_STEPS = 0.1, 1500, 300, 10_000


def score(system: Any, traj: np.ndarray, exact: np.ndarray) -> dict[str, Any]:
    """Errors at the test horizon and 10× it, energy drift along all of ``traj`` (m, 4)."""
    n = min(len(traj), len(exact))
    rel = np.linalg.norm(traj[:n] - exact[:n], axis=-1) / np.linalg.norm(exact[:n], axis=-1)
    rel = np.where(np.isfinite(rel), rel, np.inf)
    e = np.asarray(system.hamiltonian(traj))
    de = np.nan_to_num(np.abs(e - e[0]) / abs(e[0]), nan=np.inf)
    return {
        "error_test_horizon": float(rel[: TEST_STEPS + 1].max()),
        "error_10x": float(rel[: 10 * TEST_STEPS + 1].max()) if n > 10 * TEST_STEPS else "n/a",
        "energy_drift": float(de.max()),
        "drift_steps": len(traj) - 1,
    }


def roll(stepper: Any, start: np.ndarray) -> tuple[np.ndarray, float]:
    t0 = time.perf_counter()
    traj = np.asarray(pr.integrate(stepper, start, H, DRIFT_STEPS, on_failure="ignore"))
    return traj, time.perf_counter() - t0


def learn_row(system: Any, train: np.ndarray, start: np.ndarray, exact: np.ndarray,
              structure: Any, label: str) -> dict[str, Any]:  # fmt: skip
    t0 = time.perf_counter()
    stepper, report = pr.learn(train, H, structure=structure, seed=0, progress=False)
    seconds = time.perf_counter() - t0
    traj, _ = roll(stepper, start)
    kept = report.kept
    return {
        "method": label,
        "parameters": int(kept.parameters),
        "train_seconds": round(seconds, 2),
        **score(system, traj, exact),
        "explained": bool(report.explained),
        "noise": float(report.noise),
        "kept_family": kept.family,
        "kept_order": int(kept.order),
        "kept_one_step": float(kept.one_step),
        "kept_rollout": float(kept.rollout),
        "bracket": kept.bracket_text,
        "hamiltonian": kept.hamiltonian_text[:400],
        "candidates": [
            {
                "family": c.family,
                "parameters": c.parameters,
                "one_step": c.one_step,
                "rollout": c.rollout,
                "reason": c.reason[:200],
            }
            for c in report.candidates
        ],
    }


def pnn_row(pnn: Path, iterations: int, system: Any, start: np.ndarray,
            exact: np.ndarray) -> dict[str, Any]:  # fmt: skip
    """PNN's LF() on its own LFData records; z = (v, x) there, (x, v) here."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import structure_protocols as sp

    ln, mod = sp.import_pnn(pnn, None)
    torch.manual_seed(0)
    data = mod.LFData([1, 0.5, 0.5, 1], H, TRAIN_STEPS, TEST_STEPS)
    inn = ln.nn.INN(4, 2, 10, 3, 50, "sigmoid", volume_preserving=True)
    net = ln.nn.PNN(inn, ln.nn.GSympNet(4, 10, 50, "sigmoid"))
    params = sp.count(net)
    # Their records against ours (DOP853 at 1e-13), in our (x, v) order.
    theirs = np.concatenate([data.X_train[:1], data.y_train])[:, [2, 3, 0, 1]]
    ours = np.asarray(pr.reference_solution(system, theirs[0], H * np.arange(TRAIN_STEPS + 1)))
    print(f"PNN: {params} parameters, {iterations} of 2,000,000 iterations", flush=True)
    best, seconds, cpu, curve = sp.pnn_train(ln, data, net, iterations)
    t0 = time.perf_counter()
    traj = sp.pnn_rollout(best, start[None, [2, 3, 0, 1]], DRIFT_STEPS)[0][:, [2, 3, 0, 1]]
    rollout_seconds = time.perf_counter() - t0
    return {
        "method": "PNN (published code)",
        "parameters": params,
        "train_seconds": round(seconds, 1),
        "train_cpu_seconds": round(cpu, 1),
        "iterations": iterations,
        "their_iterations": 2_000_000,
        "fraction_of_theirs": round(iterations / 2_000_000, 4),
        **score(system, traj, exact),
        "rollout_seconds": round(rollout_seconds, 2),
        "best_checkpoint_iteration": int(min(curve, key=lambda r: r[2])[0]),
        "their_data_max_deviation_from_reference": float(np.abs(theirs - ours).max()),
        "loss_curve": {"columns": ["iteration", "train_mse", "test_mse"], "rows": curve},
        "notes": "their main.py LF() (device cpu): INN(4, 2, 10, 3, 50, sigmoid, volume "
        "preserving) + GSympNet(4, 10, 50, sigmoid), Adam lr 1e-3, full batch, float32; best "
        "checkpoint by test loss (their Restore); trained on their LFData records (their "
        "order-4 splitting), scored against DOP853 from the same test start as every row",
    }


def _discover_child(queue: Any, system: Any, train: np.ndarray, start: np.ndarray,
                    exact: np.ndarray, label: str) -> None:  # fmt: skip
    torch.set_num_threads(1)
    try:
        row = learn_row(system, train, start, exact, "discover", label)
    except ValueError as err:
        row = {"method": label, "notes": f"refused: {err}"}
    queue.put(row)


def discover_label(sigma: float) -> str:
    return 'pr.learn(structure="discover")' + (f", σ = {sigma:g}" if sigma else "")


def discover_row(system: Any, train: np.ndarray, start: np.ndarray, exact: np.ndarray,
                 seconds: float, sigma: float = 0.0) -> dict[str, Any]:  # fmt: skip
    """``pr.learn(structure="discover")`` in a child process, cut off after ``seconds``; with
    ``sigma`` > 0 on records with relative noise σ (``structure_protocols.noisy_records``,
    draw 0), scored against the exact test trajectory as every row."""
    label = discover_label(sigma)
    if sigma:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        import structure_protocols as sp

        train = sp.noisy_records(train, sigma, 0)
    queue: Any = mp.get_context("fork").Queue()
    child = mp.get_context("fork").Process(
        target=_discover_child, args=(queue, system, train, start, exact, label)
    )
    t0 = time.perf_counter()
    child.start()
    child.join(seconds)
    if child.is_alive():
        child.kill()
        child.join()
        row = {
            "method": label,
            "notes": f"cut off after {seconds:.0f} s on one core: no result (partial)",
        }
    else:
        row = queue.get()
        row["wall_seconds"] = round(time.perf_counter() - t0, 2)
    print({k: v for k, v in row.items() if k != "candidates"}, flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--out", type=Path, default=ROOT / "docs/learning/charged_particle_pnn.json"
    )
    parser.add_argument("--discover-seconds", type=float, default=600.0)
    parser.add_argument("--pnn", type=Path, help="checkout of jpzxshi/pnn: adds PNN's row")
    parser.add_argument("--pnn-iterations", type=int, default=20_000)
    parser.add_argument("--peer-site", type=Path, help="site directory of PNN's imports")
    parser.add_argument(
        "--only-pnn", action="store_true", help="run PNN's row alone; keep the other rows of --out"
    )
    parser.add_argument(
        "--only-discover",
        action="store_true",
        help='run the pr.learn(structure="discover") row alone; keep the other rows of --out',
    )
    parser.add_argument(
        "--sigma",
        type=float,
        default=0.0,
        help="with --only-discover: relative noise on the training records (draw 0)",
    )
    args = parser.parse_args()
    if args.sigma and not args.only_discover:
        parser.error("--sigma needs --only-discover")
    # A bad output path fails here, not after half an hour of work.
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    if args.peer_site:
        sys.path.insert(0, str(args.peer_site.resolve()))
    if args.only_pnn and args.pnn is None:
        parser.error("--only-pnn needs --pnn")
    system = load_scene(ROOT / "scenes" / "charged_particle_pnn.toml").system
    x0 = np.asarray(load_scene(ROOT / "scenes" / "charged_particle_pnn.toml").points[0])
    times = H * np.arange(TRAIN_STEPS + 1)
    train = np.asarray(pr.reference_solution(system, x0, times))[None]  # (1, 1501, 4)
    start = train[0, -1]
    exact = np.asarray(pr.reference_solution(system, start, H * np.arange(DRIFT_STEPS + 1)))
    if args.only_pnn:
        doc = json.loads(args.out.read_text())
        doc["rows"] = [r for r in doc["rows"] if r["method"] != "PNN (published code)"]
        doc["rows"].append(pnn_row(args.pnn.resolve(), args.pnn_iterations, system, start, exact))
        doc["meta"]["pnn_command"] = " ".join(sys.argv)
        print({k: v for k, v in doc["rows"][-1].items() if k != "loss_curve"}, flush=True)
        args.out.write_text(json.dumps(doc, indent=1) + "\n")
        print(f"wrote {args.out}")
        return
    if args.only_discover:
        doc = json.loads(args.out.read_text())
        label = discover_label(args.sigma)
        doc["rows"] = [r for r in doc["rows"] if r["method"] != label]
        row = discover_row(system, train, start, exact, args.discover_seconds, args.sigma)
        at = len(doc["rows"]) - (doc["rows"][-1]["method"].startswith("PNN") if doc["rows"] else 0)
        doc["rows"].insert(at, row)
        doc["meta"][f"discover_command{f'_sigma_{args.sigma:g}' if args.sigma else ''}"] = " ".join(
            sys.argv
        )
        args.out.write_text(json.dumps(doc, indent=1) + "\n")
        print(f"wrote {args.out}")
        return
    rows: list[dict[str, Any]] = []
    for label, stepper in (
        ("true system, Taylor-HJ by jets m = 3", pr.taylor_integrator(system, 3)),
        ("true system, Taylor-HJ by jets m = 5", pr.taylor_integrator(system, 5)),
        ("true system, RK4", pr.classical(system, "rk4")),
    ):
        traj, seconds = roll(stepper, start)
        rows.append({"method": label, "parameters": 0, "rollout_seconds": round(seconds, 2),
                     **score(system, traj, exact)})  # fmt: skip
        print(rows[-1], flush=True)
    rows.append(learn_row(system, train, start, exact, system,
                          "pr.learn(structure=the system: B and A given, H learned)"))  # fmt: skip
    print({k: v for k, v in rows[-1].items() if k != "candidates"}, flush=True)
    rows.append(discover_row(system, train, start, exact, args.discover_seconds))
    kept_meta: dict[str, Any] = {}
    if args.pnn is not None:
        rows.append(pnn_row(args.pnn.resolve(), args.pnn_iterations, system, start, exact))
    elif args.out.exists():
        # PNN's row (hours of training) stays unless its checkout is given.
        old = json.loads(args.out.read_text())
        rows += [r for r in old["rows"] if r["method"] == "PNN (published code)"]
        if "pnn_command" in old.get("meta", {}):
            kept_meta["pnn_command"] = old["meta"]["pnn_command"]
    meta = {
        "protocol": "PNN charged particle (LFData): 1 state (x, v) = (0.5, 1, 1, 0.5), h = 0.1, "
        "1500 training records by DOP853 at 1e-13, test 300 steps after and 3000 (10×), "
        "energy drift over 10⁴ steps from the test start",
        "scene": "scenes/charged_particle_pnn.toml",
        "command": "PYTHONPATH=python taskset -c 0 .venv/bin/python "
        "benches/charged_particle_pnn.py",
        **kept_meta,
    }
    args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
