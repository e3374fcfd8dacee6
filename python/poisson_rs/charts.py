"""Figures. Every figure is written as PNG next to the raw numbers behind it (CSV)."""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure  # the OO API: no pyplot state, no display backend

from .scene import Run, SceneResult


def write_rows(rows: Sequence[dict[str, Any]], path: Path) -> None:
    """Writes dict rows as CSV and the same rows as JSON (``path`` with suffix .json)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    path.with_suffix(".json").write_text(json.dumps(list(rows), indent=1))


def paper_figure_2(scene: SceneResult, run: Run, path: Path, max_points: int = 4000) -> Path:
    """Fig. 2: simulated (blue) and exact (red) orbits in 3-D, one panel per initial state."""
    n = len(scene.states)
    fig = Figure(figsize=(5.5 * n, 5))
    stride = max(1, len(scene.times) // max_points)
    for i in range(n):
        ax = fig.add_subplot(1, n, i + 1, projection="3d")
        ex, tr = scene.exact[i, ::stride], run.traj[i, ::stride]
        ax.plot(*ex.T, color="tab:red", lw=2.5, alpha=0.6, label="exact")
        ax.plot(*tr.T, color="tab:blue", lw=0.8, label=run.name)
        ax.set_title(f"μ₀ = {tuple(float(v) for v in scene.states[i])}")
        ax.set_xlabel("μ₁")
        ax.set_ylabel("μ₂")
        ax.set_zlabel("μ₃")
        ax.legend(loc="upper left")
    fig.suptitle(f"{len(scene.times) - 1} steps of h = {scene.h}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def paper_figure_3(scene: SceneResult, runs: Sequence[Run], path: Path) -> Path:
    """Fig. 3: |μ − μ_exact|, relative energy error and relative Casimir error against step."""
    n = len(scene.states)
    fig = Figure(figsize=(6 * n, 9))
    axes = fig.subplots(3, n, sharex=True, squeeze=False)
    steps = np.arange(len(scene.times))
    for run in runs:
        err, dh, dc = scene.errors(run), scene.energy_drift(run), scene.casimir_drift(run)
        for i in range(n):
            # Log scales: zero values (step 0) are dropped by matplotlib.
            axes[0, i].loglog(steps[1:], err[i, 1:], lw=0.8, label=run.name)
            axes[1, i].loglog(steps[1:], dh[i, 1:] + 1e-17, lw=0.8, label=run.name)
            axes[2, i].loglog(steps[1:], dc[i, 1:] + 1e-17, lw=0.8, label=run.name)
    for i in range(n):
        axes[0, i].set_title(f"μ₀ = {tuple(float(v) for v in scene.states[i])}")
        axes[0, i].set_ylabel("|μ − μ_exact|")
        axes[1, i].set_ylabel("|H − H₀| / H₀")
        axes[2, i].set_ylabel("|C − C₀| / C₀")
        axes[2, i].set_xlabel(f"step (h = {scene.h})")
        for ax in axes[:, i]:
            ax.grid(True, which="major", alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def write_trajectories(scene: SceneResult, runs: Sequence[Run], path: Path) -> Path:
    """CSV with one row per step and state: t, exact μ, and per run μ, error, H, C."""
    cols = ["state", "step", "t", "exact_1", "exact_2", "exact_3"]
    for run in runs:
        cols += [f"{run.name}_{c}" for c in ("1", "2", "3", "error", "H", "C")]
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        blocks = [
            (scene.errors(r), scene.body.hamiltonian(r.traj), scene.body.casimir(r.traj))
            for r in runs
        ]
        for i in range(len(scene.states)):
            for k, t in enumerate(scene.times):
                row: list[Any] = [i, k, f"{t:.6g}", *(f"{v:.17g}" for v in scene.exact[i, k])]
                for r, (e, hh, cc) in zip(runs, blocks, strict=True):
                    row += [f"{v:.17g}" for v in (*r.traj[i, k], e[i, k], hh[i, k], cc[i, k])]
                w.writerow(row)
    return path
