"""Writes long_run_energy_summary.csv from the long_run_energy.csv that ``poisson-rs chart``
writes: per method and decade of steps (1–10, 11–100, ..., 10⁴+1–10⁵), the median over the
scene's states of each state's largest |ΔH|/|H₀| and |ΔC|/|μ₀|^deg C in that decade, and the
largest over the states; ``last_step`` is the last step a method reached within its budget.

    poisson-rs chart scenes/heavy_top_learned.toml --out docs/heavy_top_learned
    cd docs/heavy_top_learned
    python summarize_long_run.py long_run_energy.csv long_run_energy_summary.csv
"""

from __future__ import annotations

import csv
import math
import statistics
import sys

EDGES = (0, 10, 100, 1_000, 10_000, 100_000)
METRICS = ("max_rel_dH", "max_rel_dC")


def summarize(src: str, dst: str) -> None:
    groups: dict[tuple[str, ...], dict[str, dict[str, float]]] = {}
    last: dict[tuple[str, ...], int] = {}
    with open(src, newline="") as f:
        for row in csv.DictReader(f):
            step = int(row["step"])
            d = next(i for i in range(1, len(EDGES)) if step <= EDGES[i])
            key = (row["method"], row["family"], row["h"], row["tol"], str(EDGES[d - 1] + 1))
            key += (str(EDGES[d]),)
            per_state = groups.setdefault(key, {m: {} for m in METRICS})
            last[key] = max(last.get(key, 0), step)
            for m in METRICS:
                v = float(row[m]) if row[m] else math.nan
                if not math.isnan(v):
                    per_state[m][row["state"]] = max(per_state[m].get(row["state"], 0.0), v)
    with open(dst, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(
            ["method", "family", "h", "tol", "steps_from", "steps_to", "last_step", "states"]
            + [f"{stat}_{m[4:]}" for m in METRICS for stat in ("median", "max")]
        )
        for key, per_state in groups.items():
            cells: list[str] = []
            for m in METRICS:
                v = list(per_state[m].values())
                cells += [f"{statistics.median(v):.3e}", f"{max(v):.3e}"] if v else ["", ""]
            w.writerow([*key, last[key], len(per_state[METRICS[0]]), *cells])


if __name__ == "__main__":
    summarize(sys.argv[1], sys.argv[2])
