"""Figures. Every figure is written as PNG next to the raw numbers behind it (CSV)."""

from __future__ import annotations

import csv
import io
import json
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure  # the OO API: no pyplot state, no display backend

from ..files import atomic_write_bytes
from ..protocols import system_label
from .demo import Run, SceneResult


def _savefig(fig: Figure, path: Path, **kwargs: Any) -> Path:
    """Renders ``fig`` as PNG and writes it atomically (only over a regular file or a new path)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", **kwargs)
    return atomic_write_bytes(path, buf.getvalue())


def _save_with_legend(
    fig: Figure, path: Path, handles: Sequence[Any], labels: Sequence[str], title: str | None
) -> Path:
    """One legend right of the panels, an optional title, and the PNG at ``path``."""
    fig.legend(handles, labels, loc="outside right center", fontsize=8, frameon=False)
    if title:
        fig.suptitle(wrap_title(title, fig.get_figwidth(), 10), fontsize=10)
    return _savefig(fig, path, dpi=110)


def wrap_title(title: str, width_inches: float, fontsize: float) -> str:
    """``title`` in lines that fit a figure ``width_inches`` wide, broken only at spaces
    outside brackets: a matrix, a tuple or a state stays on one line (a bracketed group longer
    than a line breaks at its own spaces)."""
    chars = max(40, int(width_inches * 72 / (0.6 * fontsize)))
    words: list[str] = []
    word, depth = "", 0
    for ch in title:
        if ch == " " and depth == 0:
            words.append(word)
            word = ""
            continue
        if ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth = max(depth - 1, 0)
        word += ch
    words.append(word)
    # A group longer than a line (a long description in parentheses) breaks at its own spaces.
    words = [part for w in words for part in (w.split(" ") if len(w) > chars else [w])]
    lines: list[str] = []
    line = ""
    for w in words:
        if line and len(line) + 1 + len(w) > chars:
            lines.append(line)
            line = w
        else:
            line = f"{line} {w}" if line else w
    lines.append(line)
    return "\n".join(lines)


def write_rows(rows: Sequence[dict[str, Any]], path: Path) -> None:
    """Writes dict rows as CSV and the same rows as JSON (``path`` with suffix .json)."""
    f = io.StringIO(newline="")
    w = csv.DictWriter(f, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    atomic_write_bytes(path, f.getvalue().encode())
    atomic_write_bytes(path.with_suffix(".json"), json.dumps(list(rows), indent=1).encode())


#: Columns of a grid of per-state panels before it wraps to a new row.
GRID_COLUMNS = 4


def figure_label(system: Any) -> str:
    """The system in a figure's title: :func:`system_label` without its matrices (a bracketed
    list of lists, such as a log-canonical system's c, with the ``name =`` before it), so that
    a title stays short and never breaks inside a matrix. Messages keep the full label."""
    text = system_label(system)
    out = ""
    i = 0
    while i < len(text):
        if text[i] == "[" and text[i + 1 :].lstrip().startswith("["):
            depth, j = 0, i
            while j < len(text):
                depth += {"[": 1, "]": -1}.get(text[j], 0)
                if depth == 0:
                    break
                j += 1
            # Drop ", c = " (or "c = ") before the matrix with it.
            out = re.sub(r",?\s*[^\s,=]*\s*=\s*$", "", out)
            i = j + 1
            continue
        out += text[i]
        i += 1
    return out.strip() or system_label(system)


def component_names(system: Any) -> tuple[str, ...]:
    """The system's names of its components (μ₁…μₙ when it has none)."""
    names = getattr(system, "component_names", None)
    if names is not None and len(names) == system.dim:
        return tuple(names)
    sub = str.maketrans("0123456789", "₀₁₂₃₄₅₆₇₈₉")
    return tuple(f"μ{str(i).translate(sub)}" for i in range(1, system.dim + 1))


def state_symbol(system: Any) -> str:
    """The letter of the system's states (its ``state_symbol``: μ on g*, x elsewhere)."""
    return str(getattr(system, "state_symbol", "x"))


def _state_label(mu0: np.ndarray, symbol: str = "μ") -> str:
    return f"{symbol}₀ = (" + ", ".join(f"{float(v):g}" for v in mu0) + ")"


def _grid(n: int, columns: int = GRID_COLUMNS) -> tuple[int, int]:
    """(rows, columns) of a grid of n panels that wraps after ``columns``."""
    cols = max(1, min(n, columns))
    return (n + cols - 1) // cols, cols


def _blocks(dim: int) -> list[tuple[int, ...]]:
    """Components in blocks of three (M and Γ on se(3)*); a last block of one or two."""
    return [tuple(range(i, min(i + 3, dim))) for i in range(0, dim, 3)]


def orbit_figure(
    scene: SceneResult, runs: Sequence[Run], path: Path, max_points: int = 4000
) -> Path:
    """Simulated and reference orbits, projected on each block of three components (3-D; a
    block of two is drawn in the plane), one panel per initial state and block; the grid wraps
    after GRID_COLUMNS panels. For the paper's rigid body this is its Fig. 2."""
    system = scene.body
    names = component_names(system)
    blocks = _blocks(scene.states.shape[1])
    n = len(scene.states)
    panels = [(i, b) for i in range(n) for b in blocks]
    nrows, ncols = _grid(len(panels))
    fig = Figure(figsize=(4.6 * ncols + 2.2, 4.4 * nrows), layout="constrained")
    stride = max(1, len(scene.times) // max_points)
    for k, (i, block) in enumerate(panels):
        three = len(block) == 3
        ax = fig.add_subplot(nrows, ncols, k + 1, projection="3d" if three else None)
        cols = list(block) if len(block) > 1 else [block[0] - 1, block[0]]
        ex = scene.exact[i, ::stride][:, cols]
        ax.plot(*ex.T, color="0.55", lw=3.0, alpha=0.6, label="reference")
        for run in runs:
            tr = run.traj[i, ::stride][:, cols]
            ax.plot(*tr.T, lw=0.8, label=run.name, color=method_style(run.name)["color"])
        ax.set_xlabel(names[cols[0]])
        ax.set_ylabel(names[cols[1]])
        if three:
            ax.set_zlabel(names[cols[2]])  # type: ignore[attr-defined]
        ax.set_title(_state_label(scene.states[i], state_symbol(scene.body)), fontsize=9)
    handles, labels = fig.axes[0].get_legend_handles_labels()
    kind = f"reference: {getattr(system, 'reference_name', 'DOP853')}"
    title = f"{figure_label(system)}: {len(scene.times) - 1} steps of h = {scene.h:g} ({kind})"
    return _save_with_legend(fig, path, handles, labels, title)


def paper_figure_2(scene: SceneResult, run: Run, path: Path, max_points: int = 4000) -> Path:
    """Fig. 2 of the paper: :func:`orbit_figure` of one run."""
    return orbit_figure(scene, [run], path, max_points)


def _line_style(name: str) -> dict[str, Any]:
    """Colour and dash of a run in the scene figures: :func:`method_style`'s, by name, so a method
    keeps its colour whatever the other runs."""
    st = method_style(name)
    return {"color": st["color"], "ls": st["ls"]}


def _drift_panels(scene: SceneResult) -> list[tuple[Any, str]]:
    from ..casimirs import casimir_label

    known = casimir_label(scene.body)
    m = state_symbol(scene.body)
    return [
        (scene.errors, f"|{m} − {m}_ref|"),
        (scene.energy_drift, "|H − H₀| / |H₀|"),
        (scene.casimir_drift, f"max |C − C₀| / |{m}₀|^deg C\n({known})"),
    ]


def _drift_column(
    axes: Sequence[Any],
    scene: SceneResult,
    runs: Sequence[Run],
    steps: np.ndarray,
    i: int,
    *,
    title_size: int | None,
) -> None:
    """Fills the three drift panels ``axes`` of state ``i`` with every run's drift against the
    step, log scales (exact zeros at 1e-17), "n/a" where the system knows no Casimir; the
    state names the first panel's title unless ``title_size`` is None."""
    for ax, (f, ylabel) in zip(axes, _drift_panels(scene), strict=True):
        for run in runs:
            values = f(run)[i, 1:]
            if np.isfinite(values).any():
                ax.loglog(
                    steps[1:], values + 1e-17, lw=0.8, label=run.name, **_line_style(run.name)
                )
        if not ax.lines:
            ax.text(0.5, 0.5, "n/a: no Casimir known for this system", ha="center",
                    va="center", transform=ax.transAxes, fontsize=9, color="0.3")  # fmt: skip
            ax.set_yticks([])
        ax.set_ylabel(ylabel, fontsize=8)
        ax.grid(True, which="major", alpha=0.3)
    if title_size is not None:
        axes[0].set_title(
            _state_label(scene.states[i], state_symbol(scene.body)), fontsize=title_size
        )
    axes[-1].set_xlabel(f"step (h = {scene.h:g})")


def _drift_grid(
    axes: Any,
    scene: SceneResult,
    runs: Sequence[Run],
    steps: np.ndarray,
    n: int,
    ncols: int,
    *,
    title_size: int,
) -> None:
    """Fills a grid of three drift panels per state (rows of 3, ``ncols`` states a row) with
    :func:`_drift_column`, and hides the cells past the ``n`` states."""
    for i in range(n):
        r0, c = 3 * (i // ncols), i % ncols
        column = [axes[r0 + p, c] for p in range(3)]
        _drift_column(column, scene, runs, steps, i, title_size=title_size)
    for i in range(n, (len(axes) // 3) * ncols):
        for p in range(3):
            axes[3 * (i // ncols) + p, i % ncols].set_visible(False)


def error_figure(scene: SceneResult, runs: Sequence[Run], path: Path) -> Path:
    """|μ − μ_ref|, relative energy error and Casimir drift against step: one block of three
    panels per initial state, the blocks wrapping after GRID_COLUMNS states. Where no Casimir
    is known the Casimir panel says so (no curve, never a zero). For the paper's scene this
    is its Fig. 3."""
    n = len(scene.states)
    nrows, ncols = _grid(n)
    fig = Figure(figsize=(5.2 * ncols + 2.6, 7.5 * nrows), layout="constrained")
    axes = fig.subplots(3 * nrows, ncols, squeeze=False, sharex=True)
    steps = np.arange(len(scene.times))
    _drift_grid(axes, scene, runs, steps, n, ncols, title_size=9)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    return _save_with_legend(
        fig, path, handles, labels, f"{figure_label(scene.body)}, h = {scene.h:g}"
    )


def paper_figure_3(scene: SceneResult, runs: Sequence[Run], path: Path) -> Path:
    """Fig. 3 of the paper: :func:`error_figure`."""
    return error_figure(scene, runs, path)


def write_trajectories(scene: SceneResult, runs: Sequence[Run], path: Path) -> Path:
    """CSV with one row per step and state: t, the reference μ, and per run μ, error, H and the
    largest Casimir drift (NaN where no Casimir is known). Components are named by the system."""
    comps = list(component_names(scene.body))
    cols = ["state", "step", "t", *(f"ref_{c}" for c in comps)]
    for run in runs:
        cols += [f"{run.name}_{c}" for c in (*comps, "error", "H", "dC")]
    f = io.StringIO(newline="")
    w = csv.writer(f)
    w.writerow(cols)
    blocks = [
        (scene.errors(r), scene.body.hamiltonian(r.traj), scene.casimir_drift(r)) for r in runs
    ]
    for i in range(len(scene.states)):
        for k, t in enumerate(scene.times):
            row: list[Any] = [i, k, f"{t:.6g}", *(f"{v:.17g}" for v in scene.exact[i, k])]
            for r, (e, hh, cc) in zip(runs, blocks, strict=True):
                row += [f"{v:.17g}" for v in (*r.traj[i, k], e[i, k], hh[i, k], cc[i, k])]
            w.writerow(row)
    return atomic_write_bytes(path, f.getvalue().encode())


def state_figure(scene: SceneResult, runs: Sequence[Run], path: Path, t_max: float = 50.0) -> Path:
    """One column per initial state (wrapping after GRID_COLUMNS states): each component
    against time up to ``t_max``, the reference solid and each run dashed, one panel per block
    of three components (M and Γ on se(3)*), then :func:`error_figure`'s three drift panels
    beneath, so that every column is full whatever the dimension; one legend of the runs, in
    the figure, right of the panels."""
    system = scene.body
    names = component_names(system)
    blocks = _blocks(scene.states.shape[1])
    n = len(scene.states)
    per = len(blocks) + 3  # panels in one state's column
    grid_rows, ncols = _grid(n)
    ratios = ([2.8] * len(blocks) + [2.5] * 3) * grid_rows
    fig = Figure(figsize=(5.2 * ncols + 2.6, sum(ratios)), layout="constrained")
    axes = fig.subplots(
        per * grid_rows, ncols, squeeze=False, gridspec_kw={"height_ratios": ratios}
    )
    k = min(len(scene.times), int(t_max / scene.h) + 1)
    t = scene.times[:k]
    steps = np.arange(len(scene.times))
    shades = ("tab:blue", "tab:orange", "tab:green")
    for i in range(n):
        r0, c = per * (i // ncols), i % ncols
        for b, block in enumerate(blocks):
            ax = axes[r0 + b, c]
            for j, colour in zip(block, shades, strict=False):
                ax.plot(t, scene.exact[i, :k, j], color=colour, lw=1.4, label=names[j])
                for run in runs:
                    ax.plot(t, run.traj[i, :k, j], color=colour, lw=0.7, ls="--", alpha=0.7)
            ax.set_xlabel("t")
            ax.legend(loc="upper right", fontsize=7, title="reference solid, methods dashed",
                      title_fontsize=6)  # fmt: skip
        axes[r0, c].set_title(_state_label(scene.states[i], state_symbol(system)), fontsize=8)
        drifts = [axes[r0 + len(blocks) + p, c] for p in range(3)]
        for ax in drifts[1:]:
            ax.sharex(drifts[0])
        _drift_column(drifts, scene, runs, steps, i, title_size=None)
    for i in range(n, grid_rows * ncols):  # the last row's empty cells
        for p in range(per):
            axes[per * (i // ncols) + p, i % ncols].set_visible(False)
    handles, labels = axes[len(blocks), 0].get_legend_handles_labels()
    return _save_with_legend(fig, path, handles, labels, f"{figure_label(system)}, h = {scene.h:g}")


# --- Work–precision charts (``poisson-rs chart``; numbers from studies.workprecision) ---

_CLASSICAL_STYLE = {
    "rk4": ("tab:green", "^"),
    "midpoint": ("tab:olive", "v"),
    "splitting": ("tab:cyan", "D"),
    "splitting4": ("tab:brown", "P"),
    "dmv": ("tab:pink", "X"),
    "dop853": ("tab:red", "*"),
    "splitting_casimir": ("tab:gray", "d"),
    # The log-coordinate splittings of a log-canonical system: the same roles as the rigid
    # body's splittings (explicit Poisson, order 2 and 4), never charted beside them.
    "log_splitting": ("tab:cyan", "D"),
    "log_splitting4": ("tab:brown", "P"),
}


#: Colours of learned models other than the default (black): none is used by another method.
LEARNED_COLOURS = (
    "tab:purple",
    "crimson",
    "teal",
    "darkgoldenrod",
    "indigo",
    "tab:pink",
    "olivedrab",
    "sienna",
    "slateblue",
    "darkcyan",
    "maroon",
    "dimgray",
)
#: Learned model → colour, assigned on first sight (stable for the process; past the palette,
#: hues a golden-ratio step apart, so no two learned models share one).
_LEARNED: dict[str, str] = {}


def _extra_colour(index: int) -> str:
    """The index-th colour past the palette: hues a golden-ratio step apart (never repeating),
    darkened to read on white."""
    import colorsys

    hue = (0.61803398875 * index) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.75, 0.55 + 0.2 * ((index * 7) % 3) / 2)
    return f"#{round(r * 255):02x}{round(g * 255):02x}{round(b * 255):02x}"


def learned_colour(method: str) -> str:
    """A colour of its own for a learned model: the slot crc32(name) picks, or the next free one
    when another model already holds it; the same name always gets the same colour once seen."""
    import zlib

    if method == "learned:default":
        return "black"
    if method not in _LEARNED:
        taken = set(_LEARNED.values())
        start = zlib.crc32(method.encode()) % len(LEARNED_COLOURS)
        free = [
            LEARNED_COLOURS[(start + k) % len(LEARNED_COLOURS)]
            for k in range(len(LEARNED_COLOURS))
            if LEARNED_COLOURS[(start + k) % len(LEARNED_COLOURS)] not in taken
        ]
        _LEARNED[method] = free[0] if free else _extra_colour(len(_LEARNED))
    return _LEARNED[method]


def method_style(method: str) -> dict[str, Any]:
    """Line style of a method, fixed by its name so every chart colours it the same way.

    Learned models are thick, each in a colour of its own (:func:`learned_colour`; black for the
    default), Taylor K in the Cayley chart blue and in the exponential chart orange (darker for
    larger K, dashed), classical methods their own colour.
    """
    from matplotlib import colormaps

    if method.startswith("learned:"):
        return {
            "color": learned_colour(method),
            "marker": "o",
            "lw": 2.2,
            "ls": "-",
            "ms": 5,
            "zorder": 5,
        }
    if method.startswith("taylor"):
        order, _, chart = method.removeprefix("taylor").partition("-")
        try:
            k = int(order)
        except ValueError:
            k = 3
        shade = 0.35 + 0.6 * min(k, 7) / 7
        cmap = colormaps["Blues" if chart == "cayley" else "Oranges"]
        ls = "-" if chart == "cayley" else "--"
        marker = "o" if chart == "cayley" else "s"
        return {"color": cmap(shade), "marker": marker, "lw": 1.3, "ls": ls, "ms": 3.5}
    color, marker = _CLASSICAL_STYLE.get(method, ("tab:gray", "h"))
    return {"color": color, "marker": marker, "lw": 1.3, "ls": ":", "ms": 5}


def _by_method(rows: Sequence[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Rows grouped by method, in first-seen order, each group ordered coarse to fine."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(r["method"], []).append(r)
    for pts in groups.values():
        pts.sort(key=lambda r: (-r["h"], -(r["tol"] if r.get("tol") is not None else 0.0)))
    return groups


def work_precision_figure(
    rows: Sequence[dict[str, Any]],
    path: Path,
    *,
    metric: str = "error_T",
    ylabel: str = "max |μ(T) − μ_exact(T)|",
    title: str = "",
    ceiling: float = 10.0,
    levels: Sequence[float] = (),
) -> Path:
    """Log–log ``metric`` against seconds per trajectory: one panel per scene, a curve per method.

    A failed run (Newton failure, non-finite state) is drawn as an × on the panel's top edge at
    its cost; a value above ``ceiling`` (the orbit is lost) as an open triangle there. Dashed
    horizontal lines mark ``levels``; open markers a learned model's steps past its training h.
    """
    from matplotlib.lines import Line2D

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    # Constrained layout keeps room for the legend outside the panels (tight_layout does not).
    fig = Figure(figsize=(6.2 * len(scenes) + 2.6, 5.6), layout="constrained")
    axes = fig.subplots(1, len(scenes), squeeze=False, sharey=True)[0]
    for ax, scene in zip(axes, scenes, strict=True):
        srows = [r for r in rows if r["scene"] == scene]
        finite = [
            r[metric]
            for r in srows
            if not r["failed"] and r[metric] is not None and math.isfinite(r[metric]) and r[metric]
        ]
        low = min(finite, default=1e-16)
        top = min(ceiling, max(finite, default=ceiling)) * 3
        edge = ax.get_xaxis_transform()  # x in data, y in axes fraction: the top edge
        for method, pts in _by_method(srows).items():
            st = method_style(method)
            ok = [
                r
                for r in pts
                if not r["failed"] and r[metric] is not None and math.isfinite(r[metric])
            ]
            inside = [r for r in ok if r[metric] <= ceiling]
            xs = [r["seconds_per_traj"] for r in inside]
            ys = [max(r[metric], 1e-17) for r in inside]  # a zero would vanish on a log axis
            ax.plot(xs, ys, label=method, **st)
            # A learned model stepping past the h it was trained for: open markers.
            ext = [(x, y) for x, y, r in zip(xs, ys, inside, strict=True) if r.get("extrapolated")]
            if ext:
                marker_style = {k: st[k] for k in ("color", "marker", "ms", "zorder") if k in st}
                ax.plot(*zip(*ext, strict=True), ls="none", mfc="white", **marker_style)
            # Off-chart markers sit on the top edge, unclipped. An empty unclipped line would
            # still count at the figure origin in the layout's bounding boxes: skip those.
            style = {"color": st["color"], "ms": 8, "ls": "none", "clip_on": False}
            over = [r["seconds_per_traj"] for r in ok if r[metric] > ceiling]
            if over:
                ax.plot(over, [0.985] * len(over), marker="^", mfc="none", transform=edge, **style)
            bad = [r["seconds_per_traj"] for r in pts if r["failed"] and r["seconds_per_traj"]]
            if bad:
                ax.plot(bad, [0.985] * len(bad), marker="x", mew=2, transform=edge, **style)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(max(low / 3, 1e-16), top)
        for level in levels:
            ax.axhline(level, color="0.6", lw=0.6, ls="--", zorder=0)
        t_end = srows[0]["T"] if srows else float("nan")
        ax.set_title(f"{scene} scene, T = {t_end:g}")
        ax.set_xlabel("wall-clock seconds per trajectory")
        ax.grid(True, which="major", alpha=0.3)
    axes[0].set_ylabel(ylabel)
    handles, labels = axes[0].get_legend_handles_labels()
    # Legend entries only for the markers drawn.
    if any(r["failed"] and r["seconds_per_traj"] for r in rows):
        handles.append(Line2D([], [], color="0.3", marker="x", mew=2, ls="none", ms=8))
        labels.append("failed run (top edge)")
    if any(not r["failed"] and r[metric] is not None and r[metric] > ceiling for r in rows):
        handles.append(Line2D([], [], color="0.3", marker="^", mfc="none", ls="none", ms=8))
        labels.append(f"> {ceiling:g} (top edge)")
    if not any(
        not r["failed"] and r[metric] is not None and math.isfinite(r[metric]) for r in rows
    ):
        for ax in axes:
            ax.text(0.5, 0.5, f"n/a: {metric} not known for this system", ha="center",
                    va="center", transform=ax.transAxes, color="0.3")  # fmt: skip
    if any(r.get("extrapolated") for r in rows):
        handles.append(Line2D([], [], color="0.3", marker="o", mfc="white", ls="none", ms=6))
        labels.append("h > trained h_max")
    return _save_with_legend(fig, path, handles, labels, title)


def long_run_figure(
    rows: Sequence[dict[str, Any]], path: Path, title: str = "", *, symbol: str = "μ"
) -> Path:
    """|ΔH|/H (max over growing windows) against time, log–log: one panel per initial state
    (titled ``symbol``₀ = the state: μ on g*, x for other structures).

    A flat curve is a bounded energy error; a drift shows as a slope (1 for linear growth).
    """
    states = list(dict.fromkeys(r["state"] for r in rows))
    nrows, ncols = _grid(len(states))  # wraps after GRID_COLUMNS states
    fig = Figure(figsize=(6.2 * ncols + 2.6, 5.2 * nrows), layout="constrained")
    grid = fig.subplots(nrows, ncols, squeeze=False, sharey=True)
    for k in range(len(states), nrows * ncols):
        grid[k // ncols, k % ncols].set_visible(False)
    axes = [grid[k // ncols, k % ncols] for k in range(len(states))]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    t_max = max(r["t"] for r in rows)
    for ax, state in zip(axes, states, strict=True):
        for method in methods:
            pts = [r for r in rows if r["state"] == state and r["method"] == method]
            if not pts:
                continue
            st = {**method_style(method), "marker": None}
            ts = [r["t"] for r in pts]
            # A run cut short (time budget, failure) says so in its label.
            label = method if pts[0].get("tol") is None else f"{method}, tol {pts[0]['tol']:.0e}"
            label += "" if ts[-1] >= t_max else f" (to t = {ts[-1]:g})"
            # Exact zeros (midpoint, DMV keep H to the last bit over short windows) sit at 1e-17.
            ax.plot(ts, [max(r["max_rel_dH"], 1e-17) for r in pts], label=label, **st)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(f"{symbol}₀ = {state}, h = {rows[0]['h']:g}")
        ax.set_xlabel("time t")
        ax.grid(True, which="major", alpha=0.3)
    for row in grid:
        row[0].set_ylabel(
            "max |H − H₀| / |H₀| over the window ending at t\n(exact zeros drawn at 1e-17)"
        )
    # Labels may differ between panels (a run cut short on one state only): merge them.
    entries: dict[str, Any] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            entries.setdefault(label, handle)
    return _save_with_legend(fig, path, list(entries.values()), list(entries), title)


def stability_figure(rows: Sequence[dict[str, Any]], path: Path, *, system: Any = None) -> Path:
    """Stability map: log₁₀ relative error at T per state (rows) and step size (columns), one
    panel per method; Newton failures are black crosses, never a colour."""
    methods = list(dict.fromkeys(r["method"] for r in rows))
    hs = sorted({float(r["h"]) for r in rows})
    labels = list(dict.fromkeys(r["state"] for r in rows))
    m = state_symbol(system)
    n = len(methods)
    cols = min(n, 4)
    nrows = (n + cols - 1) // cols
    fig = Figure(figsize=(4.2 * cols, 3.6 * nrows + 0.6))
    axes = fig.subplots(nrows, cols, squeeze=False, sharex=True, sharey=True)
    image = None
    for k, method in enumerate(methods):
        ax = axes[k // cols, k % cols]
        grid = np.full((len(labels), len(hs)), np.nan)
        for r in rows:
            if r["method"] != method:
                continue
            i, j = labels.index(r["state"]), hs.index(float(r["h"]))
            if r["converged"]:
                grid[i, j] = np.log10(max(float(r["rel_error"]), 1e-16))
            else:
                ax.plot(j, i, marker="x", color="black", ms=7, mew=2)
        image = ax.imshow(
            grid, aspect="auto", cmap="viridis", vmin=-12, vmax=0.5, interpolation="nearest"
        )
        ax.set_title(method, fontsize=10)
        ax.set_xticks(range(len(hs)), [f"{h:g}" for h in hs], rotation=90, fontsize=7)
        ax.set_yticks(range(len(labels)), labels, fontsize=7)
    for k in range(n, nrows * cols):
        axes[k // cols, k % cols].set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("h")
    if image is not None:
        fig.colorbar(
            image,
            ax=axes,
            shrink=0.8,
            label=f"log₁₀ |{m}(T) − {m}_ref(T)| / |{m}₀|  (× = failed step)",
        )
    if system is not None:
        title = f"Stability map: {figure_label(system)}"
        fig.suptitle(wrap_title(title, fig.get_figwidth(), 11), fontsize=11)
    return _savefig(fig, path, dpi=110, bbox_inches="tight")


#: The ``gid`` of the stability summary's panel of failed steps (one row per method).
FAILURES_GID = "failed-steps"


def stability_summary_figure(
    rows: Sequence[dict[str, Any]], path: Path, *, system: Any = None
) -> Path:
    """Worst relative error at T, worst |ΔH|/H and worst |ΔC|/C over the states against h, per
    method; beneath, one row per method with a × at each step size where a step failed for
    some state, so that every failing method shows however many fail at the same h."""
    methods = list(dict.fromkeys(r["method"] for r in rows))
    strip = 0.35 * len(methods) + 0.9
    fig = Figure(figsize=(15, 4.5 + strip), layout="constrained")
    grid = fig.add_gridspec(2, 3, height_ratios=[4.5, strip])
    axes = [fig.add_subplot(grid[0, c]) for c in range(3)]
    fails = fig.add_subplot(grid[1, :], sharex=axes[0])
    fails.set_gid(FAILURES_GID)
    m = state_symbol(system)
    keys = [
        ("rel_error", f"worst |{m}(T) − {m}_ref(T)| / |{m}₀|"),
        ("max_rel_dH", "worst max |H − H₀| / |H₀|"),
        ("max_rel_dC", f"worst max |C − C₀| / |{m}₀|^deg C"),
    ]
    any_failed = False
    for row, method in enumerate(methods):
        mine = [r for r in rows if r["method"] == method]
        hs = sorted({float(r["h"]) for r in mine})
        colour = method_style(method)["color"]
        for ax, (key, _) in zip(axes, keys, strict=True):
            worst = []
            for h in hs:
                vals = [float(r[key]) for r in mine if float(r["h"]) == h and r["converged"]]
                vals = [v for v in vals if math.isfinite(v)]  # NaN: not known, not zero
                worst.append(max(vals) + 1e-17 if vals else np.nan)
            ax.loglog(hs, worst, marker="o", ms=3, lw=1, label=method, color=colour)
        failed = [h for h in hs if any(not r["converged"] for r in mine if float(r["h"]) == h)]
        if failed:
            any_failed = True
            # Its own row: a × of one method never hides another's at the same h.
            fails.plot(failed, [row] * len(failed), ls="none", marker="x", ms=8, mew=2,
                       color=colour, label=method)  # fmt: skip
    for ax, (key, label) in zip(axes, keys, strict=True):
        if not any(math.isfinite(float(r[key])) for r in rows if r["converged"]):
            ax.text(0.5, 0.5, "n/a: no Casimir known for this system", ha="center",
                    va="center", transform=ax.transAxes, color="0.3")  # fmt: skip
        ax.set_xlabel("step size h")
        ax.set_ylabel(label)
        ax.grid(True, which="major", alpha=0.3)
    fails.set_xscale("log")
    fails.set_ylim(len(methods) - 0.5, -0.5)
    fails.set_yticks(range(len(methods)), methods, fontsize=8)
    fails.set_xlabel("step size h")
    fails.grid(True, which="major", alpha=0.3)
    fails.set_title(
        "× : a step failed for some state" if any_failed else "no step failed", fontsize=9
    )
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside right center", fontsize=8)
    what = f"{figure_label(system)}: " if system is not None else ""
    fig.suptitle(wrap_title(f"{what}where methods break", fig.get_figwidth(), 12))
    return _savefig(fig, path, dpi=110)


# --- Size against accuracy and speed (``poisson-rs sweep``; numbers from studies.sweep) ---

_DEPTH_COLOURS = {1: "tab:cyan", 2: "tab:blue", 3: "tab:green"}


def sweep_figure(rows: Sequence[dict[str, Any]], path: Path, *, title: str = "") -> Path:
    """Error at T from (1,1,2) and from (3,2,0), and rollout steps/s, against parameter count
    (log–log), from :func:`poisson_rs.studies.sweep.run_sweep` rows.

    Each trained seed is a small dot and each architecture's median a large one (colour: depth),
    medians of one depth joined by a line; a shipped model is a star labelled with where it was
    trained; each Taylor series (no network) is a horizontal line. A non-finite error (a failed
    rollout) is an × on the panel's top edge.
    """
    from .sweep import medians

    fig = Figure(figsize=(17, 5.4), layout="constrained")
    axes = fig.subplots(1, 3)
    panels = [
        ("error_112", "|μ(T) − μ_exact(T)|, μ₀ = (1, 1, 2)"),
        ("error_320", "|μ(T) − μ_exact(T)|, μ₀ = (3, 2, 0)"),
        ("steps_per_s", "rollout steps/s (Rust, batch 64)"),
    ]
    learned = [r for r in rows if r["kind"] == "learned"]
    med = medians(learned)
    for ax, (key, ylabel) in zip(axes, panels, strict=True):
        edge = ax.get_xaxis_transform()
        for depth in sorted({r["depth"] for r in med}):
            colour = _DEPTH_COLOURS.get(depth, "tab:gray")
            pts = sorted((r for r in med if r["depth"] == depth), key=lambda r: r["params"])
            seeds = [r for r in learned if r["depth"] == depth]
            ok = [r for r in seeds if math.isfinite(r[key])]
            ax.plot(
                [r["params"] for r in ok],
                [r[key] for r in ok],
                ls="none",
                marker="o",
                ms=3.5,
                alpha=0.45,
                color=colour,
            )
            bad = [r["params"] for r in seeds if not math.isfinite(r[key])]
            if bad:
                ax.plot(
                    bad,
                    [0.985] * len(bad),
                    ls="none",
                    marker="x",
                    mew=2,
                    ms=8,
                    color=colour,
                    transform=edge,
                    clip_on=False,
                )
            good = [r for r in pts if r[key] is not None and math.isfinite(r[key])]
            ax.plot(
                [r["params"] for r in good],
                [r[key] for r in good],
                marker="o",
                ms=7,
                lw=1.2,
                color=colour,
                label=f"depth {depth}: median of {pts[0]['n_seeds']} seeds" if pts else None,
            )
            for r in good:
                ax.annotate(
                    r["model"],
                    (r["params"], r[key]),
                    textcoords="offset points",
                    xytext=(4, -11) if depth >= 3 else (4, 5),  # apart from depth 2's labels
                    fontsize=7,
                    color=colour,
                )
        for r in rows:
            if r["kind"] != "shipped" or not math.isfinite(r[key]):
                continue
            where = f", trained on {r['trained_on']}" if r["trained_on"] else ""
            if r["train_seconds"] is not None:
                where += f" in {r['train_seconds']:.0f} s"
            ax.plot(
                r["params"],
                r[key],
                marker="*",
                ms=13,
                ls="none",
                color="tab:purple",
                label=f"shipped {r['model']}: {r['widths']}{where}",
            )
        for r in rows:
            if r["kind"] != "taylor" or not math.isfinite(r[key]):
                continue
            st = method_style(r["model"])
            label = f"{r['model']} (no network)"
            ax.axhline(r[key], color=st["color"], ls=st["ls"], lw=1.1, label=label)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("trainable parameters")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="major", alpha=0.3)
    axes[0].set_title("error at T = 10, h = 0.1", fontsize=10)
    axes[1].set_title("error at T = 10, h = 0.1", fontsize=10)
    axes[2].set_title("speed (higher is faster)", fontsize=10)
    handles, labels = axes[0].get_legend_handles_labels()
    return _save_with_legend(fig, path, handles, labels, title)
