"""Scene files: a rigid body, the states and steps it is integrated with, and the accuracy an
integrator must reach there; training driven by that target.

A scene is a TOML file::

    name = "paper"                          # optional; default: the file's stem
    description = "..."                     # optional

    [system]
    inertia = [1.5, 2.0, 2.5]               # principal moments I₁, I₂, I₃ > 0
    # kind = "heavy_top"                    # optional: "rigid_body" (default), "heavy_top"
    # mgl = 0.981                           #   (with inertia, mgl, com) or "lie_poisson" (with
    # com = [0.0, 0.0, 1.0]                 #   algebra and hamiltonian: a system's to_dict());
    # algebra = "se3"                       #   algebra may be "so3", "se3" or "sl2" instead of
    # hamiltonian = { dim = 6, terms = [[2, 0, 0, 0, 0, 0, 0.5], ...] }   # its constants
    # system_file = "kirchhoff.json"        # or: the whole system from a JSON file of
                                            #   system.to_dict(), relative to the scene

    [states]                                # at least one of points and shell
    points = [[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]]
    shell = { r_min = 1.5, r_max = 2.9, n = 16, seed = 1 }   # held-out random states

    [steps]
    h = 0.1                                 # a step size, or a list of them
    horizon = 10.0                          # time T, a whole number of steps of every h

    [target]                                # at least one key
    error = 5.6e-6                          # max |μ(T) − μ_exact(T)| over states and h
    energy = 2.5e-8                         # max |H − H₀|/H₀ over [0, T], states and h
    newton = "all"                          # every Newton solve must converge

    [model]                                 # optional TrainConfig overrides, plus
    chart = "exp"                           #   evaluate_every (iterations between rollouts)
    widths = [4]                            #   and margin ([lo, hi] on the |μ| range)
    sampling = "scene"                      # optional: half of each batch near the exact
                                            #   orbits of the scene's states up to its horizon

    [select]                                # optional: what ``poisson-rs select`` looks for
    target = [1e-3, 1e-6]                   # largest metric allowed (one selection per value)
    metric = "error"                        # "error": max |μ(T) − μ_ref(T)|/|μ₀|; "energy":
                                            #   max |H − H₀|/|H₀|; "casimir": max |C − C₀|/|μ₀|^d
    T = 10.0                                # horizon (default: steps.horizon)
    h = 0.1                                 # optional: measure at this step only
    models = ["paper_h01"]                  # optional: learned models (default: the shipped ones)

Outside the rigid body, states are ``points`` of the system's dimension (for the heavy top
(M₁, M₂, M₃, Γ₁, Γ₂, Γ₃)); the reference is DOP853 at rtol = atol = 1e-13, and ``casimir`` is the
largest |C − C₀|/|μ₀|² over the system's Casimirs (|Γ|² and M·Γ for the heavy top).

The shell states are drawn with their own seed (|μ| uniform in [r_min, r_max], directions
uniform on the sphere), so they are held out from the training points. Errors are Euclidean
norms, against :func:`~poisson_rs.exact_solution`.
"""

from __future__ import annotations

import dataclasses
import shlex
import time
import tomllib
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .integrators import BisectionIntegrator, Stepper, integrate
from .protocols import PoissonSystem
from .reference import reference_solution
from .structures.lie_poisson import LieAlgebra, RigidBody
from .tables import number as _number

_SE3 = LieAlgebra.se3()

if TYPE_CHECKING:
    from .generating import GeneratingFunction
    from .train import TrainConfig

_TOP_KEYS = ("name", "description", "system", "states", "steps", "target", "model", "select")
_SECTION_KEYS: dict[str, tuple[str, ...]] = {
    "select": ("target", "T", "h", "models", "metric"),
    "states": ("points", "shell"),
    "steps": ("h", "horizon"),
    "target": ("error", "energy", "newton"),
}
_SHELL_KEYS = ("r_min", "r_max", "n", "seed")
_NEWTON = ("all",)

# [model] keys: TrainConfig fields (inertia comes from [system]) and their TOML types, plus the
# two knobs of target-driven training that are not part of a TrainConfig.
_MODEL_TYPES: dict[str, str] = {
    "chart": "str",
    "widths": "ints",
    "inputs": "str",
    "taylor_order": "int",
    "mlp_power": "int",
    "domain": "str",
    "r_min": "float",
    "r_max": "float",
    "half_width": "float",
    "h_max": "float",
    "batch": "int",
    "n_points": "int",
    "iterations": "int",
    "lr": "float",
    "schedule": "str",
    "seed": "int",
    "dtype": "str",
    "device": "str",
    "derivatives": "str",
    "lbfgs_iterations": "int",
    "data_weight": "float",
    "data_points": "int",
    "data_h": "float",
    "sampling": "str",
    "sampling_fraction": "float",
    "sampling_noise": "float",
    "evaluate_every": "int",
    "margin": "floats",
}
DEFAULT_EVALUATE_EVERY = 100
"""Adam iterations between two rollouts of the scene during target-driven training."""
DEFAULT_MARGIN = (0.8, 1.2)
"""Training shell = (lo·min |μ₀|, hi·max |μ₀|). The Newton iterates p sit near |μ| (within 0.3%
in the exponential chart at h = 0.5, up to 28% below it in the Cayley chart); with homogeneous
inputs only τ = |p|t ≤ r_max·h_max matters, so the margin mainly buys headroom in τ."""


@dataclass(frozen=True)
class ShellStates:
    """n held-out states with |μ| uniform in [r_min, r_max] and uniform directions in R^dim."""

    r_min: float
    r_max: float
    n: int
    seed: int = 0
    dim: int = 3

    def sample(self) -> np.ndarray:
        """The states, (n, dim) float64; the same for the same seed."""
        rng = np.random.default_rng(self.seed)
        d = rng.normal(size=(self.n, self.dim))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return d * rng.uniform(self.r_min, self.r_max, size=(self.n, 1))


@dataclass(frozen=True)
class Target:
    """What an integrator must reach on a scene; None: not asked."""

    error: float | None = None
    """max |μ(T) − μ_exact(T)| over the scene's states and step sizes (units of μ)."""
    energy: float | None = None
    """max |H(μ_k) − H(μ₀)| / H(μ₀) over the steps up to T, the states and step sizes."""
    newton: str | None = None
    """"all": every Newton solve of every step must converge."""

    def as_dict(self) -> dict[str, Any]:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


@dataclass(frozen=True)
class SelectSpec:
    """The [select] table: what :func:`~poisson_rs.select` is asked on the scene's states."""

    targets: tuple[float, ...]
    """Relative errors max |μ(T) − μ_ref(T)|/|μ₀| (unit-less), one selection each."""
    T: float
    h: float | None = None
    models: tuple[str, ...] | None = None
    metric: str = "error"
    """What the targets bound: "error", "energy" or "casimir" (see :func:`~poisson_rs.select`)."""


@dataclass(frozen=True)
class Scene:
    """A parsed, validated scene file (see the module docstring for the format)."""

    name: str
    inertia: tuple[float, float, float]
    points: tuple[tuple[float, float, float], ...]
    shell: ShellStates | None
    h: tuple[float, ...]
    """Step sizes (time units), each dividing ``horizon``."""
    horizon: float
    target: Target
    model: Mapping[str, Any] = field(default_factory=dict)
    """TrainConfig overrides from [model] (widths as a tuple)."""
    evaluate_every: int = DEFAULT_EVALUATE_EVERY
    margin: tuple[float, float] = DEFAULT_MARGIN
    description: str = ""
    path: Path | None = None
    system: Any = None
    """The system integrated (a LiePoissonSystem, or a log-canonical system); None (filled
    in): the rigid body of ``inertia``."""
    select: SelectSpec | None = None

    def __post_init__(self) -> None:
        if self.system is None:
            object.__setattr__(self, "system", RigidBody(self.inertia))

    @property
    def lie_system(self) -> Any:
        """The scene's system (never None after construction), of any structure."""
        assert self.system is not None
        return self.system

    @property
    def body(self) -> Any:
        """The scene's system: an alias of :attr:`system`, kept one release for the rigid-body
        scenes that used it (any scene answers it now)."""
        assert self.system is not None
        return self.system

    def states(self) -> np.ndarray:
        """The scene's initial states, points first then the shell's: (n, dim) float64."""
        dim = self.lie_system.dim
        parts = [np.asarray(self.points, dtype=np.float64).reshape(-1, dim)]
        if self.shell is not None:
            parts.append(self.shell.sample())
        return np.concatenate(parts)

    def n_steps(self, h: float) -> int:
        """Steps of size h to the horizon."""
        return round(self.horizon / h)


# ---------------------------------------------------------------------------------------------
# Parsing and validation


def _integer(value: Any, key: str, *, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ValueError(f"scene key '{key}' must be an integer >= {low}, got {value!r}")
    return value


def _table(
    data: Mapping[str, Any], key: str, allowed: tuple[str, ...] | None, *, prefix: str = ""
) -> Mapping[str, Any]:
    """The sub-table ``data[key]`` (empty if absent), refusing keys outside ``allowed`` (None:
    the caller checks them); ``prefix`` is the dotted path of ``data`` itself, for the
    messages."""
    value = data.get(key, {})
    name = f"{prefix}{key}"
    if not isinstance(value, Mapping):
        raise ValueError(f"scene key '{name}' must be a table, got {value!r}")
    for k in value:
        if allowed is not None and k not in allowed:
            raise ValueError(
                f"scene key '{name}.{k}' is not known; expected one of {', '.join(allowed)}"
            )
    return value


def _model_overrides(raw: Mapping[str, Any]) -> dict[str, Any]:
    """[model] values checked for type (their ranges are checked by TrainConfig.validate)."""
    out: dict[str, Any] = {}
    for k, v in raw.items():
        key = f"model.{k}"
        kind = _MODEL_TYPES[k]
        if kind == "str":
            if not isinstance(v, str):
                raise ValueError(f"scene key '{key}' must be a string, got {v!r}")
            out[k] = v
        elif kind == "int":
            out[k] = _integer(v, key, low=0)
        elif kind == "float":
            out[k] = _number(v, key, positive=False)
        elif kind == "ints":
            if not isinstance(v, list):
                raise ValueError(f"scene key '{key}' must be a list of integers, got {v!r}")
            out[k] = tuple(_integer(w, key, low=1) for w in v)
        else:  # floats
            if not isinstance(v, list) or len(v) != 2:
                raise ValueError(f"scene key '{key}' must be a list of 2 numbers, got {v!r}")
            out[k] = tuple(_number(w, key) for w in v)
    return out


#: Algebras a scene may name instead of giving the structure constants.
def _lie_system(raw: Mapping[str, Any], path: Path | None = None) -> PoissonSystem:
    """The [system] table as a system, read by the structure that owns its ``kind`` (the rigid
    body when absent, or "lie_poisson" when it gives an ``algebra``); ``system_file`` names a
    JSON file of any system's ``to_dict()`` (relative to the scene) instead of the whole table.
    ValueError naming the key otherwise."""
    from .structures import system_from_scene_table

    if "system_file" in raw:
        extra = [k for k in raw if k != "system_file"]
        if extra:
            raise ValueError(f"scene key 'system.{extra[0]}': give system_file alone")
        return _system_file(raw["system_file"], path)
    return system_from_scene_table(raw, "lie_poisson" if "algebra" in raw else "rigid_body")


def _system_file(value: Any, path: Path | None) -> PoissonSystem:
    """The system of a JSON file named by ``system.system_file`` (relative to the scene)."""
    import json

    from .files import check_input_file
    from .untrusted import parsing

    if not isinstance(value, str) or not value:
        raise ValueError(f"scene key 'system.system_file' must be a file name, got {value!r}")
    file = Path(value)
    if not file.is_absolute() and path is not None:
        file = path.parent / file
    check_input_file(file, max_bytes=1 << 20, what="system file")
    with parsing(f"system file {file}"):
        data = json.loads(file.read_text(encoding="utf-8"))
        if not isinstance(data, dict):
            raise ValueError("must hold a JSON object (a system's to_dict())")
        from .structures import system_from_dict

        return system_from_dict(data)


def _select_spec(raw: Mapping[str, Any], horizon: float) -> SelectSpec | None:
    """The [select] table checked (None when absent)."""
    if not raw:
        return None
    if "target" not in raw:
        raise ValueError("scene key 'select.target' is missing")
    targets = raw["target"] if isinstance(raw["target"], list) else [raw["target"]]
    if not targets:
        raise ValueError("scene key 'select.target' must not be an empty list")
    T = _number(raw.get("T", horizon), "select.T")
    h = _number(raw["h"], "select.h") if "h" in raw else None
    if h is not None:
        n = round(T / h)
        if n < 1 or abs(n * h - T) > 1e-9 * T:
            raise ValueError(f"scene key 'select.T' = {T} must be a whole number of steps h = {h}")
    models = raw.get("models")
    if models is not None and not (
        isinstance(models, list) and all(isinstance(m, str) and m for m in models)
    ):
        raise ValueError(f"scene key 'select.models' must be a list of model names, got {models!r}")
    metric = raw.get("metric", "error")
    if metric not in ("error", "energy", "casimir"):
        raise ValueError(
            f'scene key \'select.metric\' must be "error", "energy" or "casimir", got {metric!r}'
        )
    return SelectSpec(
        tuple(_number(v, "select.target") for v in targets),
        T,
        h,
        None if models is None else tuple(models),
        metric,
    )


def parse_scene(data: Mapping[str, Any], *, name: str, path: Path | None = None) -> Scene:
    """A Scene from a decoded TOML document; ``name`` is used when the file sets none.

    Raises ValueError naming the offending key ('steps.h', 'states.shell.r_max', ...).
    """
    for k in data:
        if k not in _TOP_KEYS:
            raise ValueError(
                f"scene key '{k}' is not known; expected one of {', '.join(_TOP_KEYS)}"
            )
    name = data.get("name", name)
    if not isinstance(name, str) or not name:
        raise ValueError(f"scene key 'name' must be a non-empty string, got {name!r}")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise ValueError(f"scene key 'description' must be a string, got {description!r}")

    # The structure that owns the table's kind checks its keys.
    system = _table(data, "system", None)
    lie_system = _lie_system(system, path)
    # Training's TrainConfig takes the rigid body's inertia (its default where there is none).
    i1, i2, i3 = (float(v) for v in getattr(lie_system, "inertia", (1.5, 2.0, 2.5)))
    dim = lie_system.dim

    states = _table(data, "states", _SECTION_KEYS["states"])
    if "points" not in states and "shell" not in states:
        raise ValueError("scene key 'states' needs 'points' or 'shell' (or both)")
    points: list[tuple[float, float, float]] = []
    raw_points = states.get("points", [])
    if not isinstance(raw_points, list):
        raise ValueError(
            f"scene key 'states.points' must be a list of [x, y, z], got {raw_points!r}"
        )
    for j, pt in enumerate(raw_points):
        key = f"states.points[{j}]"
        if not isinstance(pt, list) or len(pt) != dim:
            raise ValueError(f"scene key '{key}' must be {dim} numbers, got {pt!r}")
        values = tuple(_number(v, key, positive=False) for v in pt)
        if not lie_system.in_domain(np.array([values]))[0]:
            raise ValueError(
                f"scene key '{key}' = {list(values)} must lie in the "
                f"{lie_system.domain_text()} domain of {_system_label(lie_system)}"
            )
        # H₀ = 0 there: the relative energy error is undefined (and μ = 0 never moves).
        if not any(values):
            raise ValueError(f"scene key '{key}' must not be the zero state")
        points.append(values)  # type: ignore[arg-type]
    shell = None
    if "shell" in states:
        raw_shell = _table(states, "shell", _SHELL_KEYS, prefix="states.")
        for k in ("r_min", "r_max", "n"):
            if k not in raw_shell:
                raise ValueError(f"scene key 'states.shell.{k}' is missing")
        r_min = _number(raw_shell["r_min"], "states.shell.r_min")
        r_max = _number(raw_shell["r_max"], "states.shell.r_max")
        if r_max < r_min:
            raise ValueError(f"scene key 'states.shell.r_max' must be >= r_min, got {r_max}")
        shell = ShellStates(
            r_min,
            r_max,
            _integer(raw_shell["n"], "states.shell.n", low=1),
            _integer(raw_shell.get("seed", 0), "states.shell.seed", low=0),
            dim,
        )
    if not points and shell is None:
        raise ValueError("scene key 'states.points' is empty and there is no shell")

    steps = _table(data, "steps", _SECTION_KEYS["steps"])
    for k in ("h", "horizon"):
        if k not in steps:
            raise ValueError(f"scene key 'steps.{k}' is missing")
    raw_h = steps["h"] if isinstance(steps["h"], list) else [steps["h"]]
    if not raw_h:
        raise ValueError("scene key 'steps.h' must not be an empty list")
    hs = tuple(_number(v, "steps.h") for v in raw_h)
    horizon = _number(steps["horizon"], "steps.horizon")
    for h in hs:
        n = round(horizon / h)
        if n < 1 or abs(n * h - horizon) > 1e-9 * horizon:
            raise ValueError(
                f"scene key 'steps.horizon' = {horizon} must be a whole number of steps h = {h}"
            )

    n_states = len(points) + (shell.n if shell is not None else 0)
    if n_states > _MAX_SCENE_STATES:
        raise ValueError(f"scene has {n_states} states, more than {_MAX_SCENE_STATES}")
    if shell is not None:
        outside = ~lie_system.in_domain(shell.sample())
        if outside.any():
            raise ValueError(
                f"scene key 'states.shell': {int(outside.sum())} of its {shell.n} states lie "
                f"outside the {lie_system.domain_text()} domain of {_system_label(lie_system)}; "
                "give 'states.points' instead"
            )
    records = n_states * sum(round(horizon / h) + 1 for h in hs)
    if records > _MAX_SCENE_RECORDS:
        raise ValueError(
            f"scene key 'steps.horizon' = {horizon}: {records} recorded states (states × steps) "
            f"would not fit in memory (at most {_MAX_SCENE_RECORDS})"
        )

    tgt = _table(data, "target", _SECTION_KEYS["target"])
    if not tgt:
        raise ValueError("scene key 'target' needs at least one of error, energy, newton")
    newton = tgt.get("newton")
    if newton is not None and newton not in _NEWTON:
        raise ValueError(f"scene key 'target.newton' must be 'all', got {newton!r}")
    target = Target(
        error=_number(tgt["error"], "target.error") if "error" in tgt else None,
        energy=_number(tgt["energy"], "target.energy") if "energy" in tgt else None,
        newton=newton,
    )

    if "model" in data and not getattr(lie_system, "trainable", False):
        raise ValueError(
            "scene key 'model': training a learned S is not available for "
            + _system_label(lie_system)
        )
    model = _model_overrides(_table(data, "model", tuple(_MODEL_TYPES)))
    evaluate_every = model.pop("evaluate_every", DEFAULT_EVALUATE_EVERY)
    if evaluate_every < 1:
        raise ValueError(f"scene key 'model.evaluate_every' must be >= 1, got {evaluate_every}")
    margin = model.pop("margin", DEFAULT_MARGIN)
    if not margin[0] <= 1.0 <= margin[1]:
        raise ValueError(f"scene key 'model.margin' must be [lo <= 1, hi >= 1], got {list(margin)}")
    select = _select_spec(_table(data, "select", _SECTION_KEYS["select"]), horizon)
    scene = Scene(
        name=name,
        inertia=(i1, i2, i3),
        points=tuple(points),
        shell=shell,
        h=hs,
        horizon=horizon,
        target=target,
        model=model,
        evaluate_every=evaluate_every,
        margin=margin,
        description=description,
        path=path,
        system=lie_system,
        select=select,
    )
    if getattr(lie_system, "trainable", False):
        try:
            derive_config(scene).validate()
        except ValueError as e:
            raise ValueError(f"scene key 'model': {e}") from e
    return scene


def _system_label(system: Any) -> str:
    from .protocols import system_label

    return system_label(system)


def load_scene(path: str | Path) -> Scene:
    """Reads and validates a scene file. Raises FileNotFoundError, or ValueError naming the key
    (or the TOML syntax error)."""
    from .files import check_input_file

    path = check_input_file(path, max_bytes=_MAX_SCENE_BYTES, what="scene file")
    with path.open("rb") as f:
        try:
            data = tomllib.load(f)
        except tomllib.TOMLDecodeError as e:
            raise ValueError(f"scene file {path} is not valid TOML: {e}") from e
        except UnicodeDecodeError:
            raise ValueError(f"scene file {path} is not UTF-8 text (a binary file?)") from None
        except RecursionError:
            raise ValueError(f"scene file {path}: nested too deeply") from None
    from .untrusted import parsing

    # Whatever else goes wrong in a hostile file is one ValueError naming the file.
    with parsing(f"scene file {path}"):
        return parse_scene(data, name=path.stem, path=path)


#: Largest scene file read (a scene is a few hundred bytes of TOML).
_MAX_SCENE_BYTES = 1 << 20
#: Most states a scene may hold, and most recorded states (states × steps, all step sizes) its
#: evaluation keeps: 10⁸ states of 3 float64 are 2.4 GB.
_MAX_SCENE_STATES = 100_000
_MAX_SCENE_RECORDS = 100_000_000


# ---------------------------------------------------------------------------------------------
# Training configuration and evaluation


def derive_config(scene: Scene, **overrides: Any) -> TrainConfig:
    """The TrainConfig a scene asks for: shell domain from the |μ| its states visit, h_max from its
    largest step, then its [model] values, then ``overrides``; with ``sampling = "scene"`` the
    sampled orbits are the scene's states up to its horizon unless ``overrides`` name others.

    |μ| is a Casimir, kept by the exact flow and by every bisection step, so a trajectory stays
    at its |μ₀|: the shell spans margin[0]·min |μ₀| to margin[1]·max |μ₀|.
    """
    from .train import TrainConfig

    system = scene.lie_system
    if not getattr(system, "trainable", False):
        raise ValueError(
            f"scene {scene.name!r}: training a learned S is not available for "
            f"{_system_label(system)}; its Taylor-HJ and classical methods run in demo, chart, "
            "stability and select"
        )
    r = np.linalg.norm(scene.states(), axis=1)
    base: dict[str, Any] = {"inertia": scene.inertia}
    if "cayley" not in system.taylor_charts():
        # Systems without the rigid body's Cayley series: the exp chart and t,p inputs unless
        # H is homogeneous quadratic.
        base.update(system=system.to_dict(), chart="exp")
        if not system.polynomial.is_homogeneous(2):
            base["inputs"] = "t,p"
    base |= {
        "domain": "shell",
        "r_min": float(scene.margin[0] * r.min()),
        "r_max": float(scene.margin[1] * r.max()),
        "h_max": max(scene.h),
    }
    if system.algebra == _SE3:
        base |= _top_domain(scene)
    base.update(scene.model)
    base.update(overrides)
    if base.get("sampling") == "scene":
        # Scene sampling follows this scene's own orbits: every state, up to its horizon.
        base.setdefault("sampling_states", tuple(map(tuple, scene.states().tolist())))
        base.setdefault("sampling_horizon", scene.horizon)
    return TrainConfig(**base)


def _top_domain(scene: Scene) -> dict[str, Any]:
    """The "top" training domain of an se(3)* scene: |Γ| within the margins of the states' |Γ|
    (a Casimir: it stays at |Γ₀|), |Mᵢ| up to margin[1] times the largest |Mᵢ| the reference
    orbits reach by the horizon (M is not conserved; 201 samples of each orbit)."""
    mu0 = scene.states()
    gamma = np.linalg.norm(mu0[:, 3:], axis=1)
    times = np.linspace(0.0, scene.horizon, 201)
    orbits = reference_solution(scene.lie_system, mu0, times)
    m_max = float(np.abs(orbits[..., :3]).max())
    return {
        "domain": "top",
        "r_min": float(scene.margin[0] * gamma.min()),
        "r_max": float(scene.margin[1] * gamma.max()),
        "half_width": float(scene.margin[1] * max(m_max, 1e-3)),
    }


def evaluate(model: Stepper, scene: Scene, *, strict: bool = True) -> dict[str, Any]:
    """Rolls ``model`` out on every state and step size of the scene (in Rust) and measures it.

    Returns a JSON-able dict: ``error`` (max |μ(T) − μ_exact(T)|), ``energy`` (max relative
    |ΔH| over [0, T]), ``casimir`` (max relative |ΔC|), ``converged`` (every Newton solve),
    ``n_failed`` (trajectories that failed), ``target_met``, and ``per_h``: for each h, the
    per-state lists ``error``, ``energy``, ``converged`` (points first, then the shell). A failed
    trajectory has error and energy inf. ``strict`` is passed on to :func:`integrate` (a learned
    model refuses h beyond its h_max).
    """
    system = scene.lie_system
    own = getattr(model, "system", None)
    if own is not None and own != system:
        raise ValueError(f"the model is for {own!r}, the scene {scene.name!r} for {system!r}")
    body = system
    mu0 = scene.states()
    exact = system.reference(mu0, [scene.horizon])[:, 0]
    h0, c0 = body.hamiltonian(mu0), _casimirs(system, mu0)
    # Casimir drift relative to |μ₀|^d for a Casimir of degree d (for the rigid body, C₀
    # itself); absolute (d = 0) for the log-form Casimirs Σ k_i ln x_i of a log-canonical system.
    from .casimirs import casimir_degrees

    degrees = casimir_degrees(system) or (0,)
    c_scale = np.linalg.norm(mu0, axis=1) ** max(degrees)
    per_h = []
    for h in scene.h:
        with warnings.catch_warnings():
            # Failures are reported in the result; out-of-domain states are the scene's choice.
            warnings.simplefilter("ignore", RuntimeWarning)
            traj, info = integrate(
                model,
                mu0,
                h,
                scene.n_steps(h),
                return_info=True,
                on_failure="ignore",
                strict=strict,
            )
        err = np.linalg.norm(traj[:, -1] - exact, axis=-1)
        with np.errstate(invalid="ignore"):
            dh = np.abs(body.hamiltonian(traj) - h0[:, None]).max(axis=1) / np.abs(h0)
            dc = np.abs(_casimirs(system, traj) - c0[:, None]).max(axis=(1, 2)) / c_scale
        # NaN (after a Newton failure) must fail any threshold: report it as inf.
        bad = ~info.converged | ~np.isfinite(err)
        err, dh, dc = (np.where(bad | ~np.isfinite(a), np.inf, a) for a in (err, dh, dc))
        per_h.append(
            {
                "h": h,
                "n_steps": scene.n_steps(h),
                "error": err.tolist(),
                "energy": dh.tolist(),
                "casimir": dc.tolist(),
                "converged": info.converged.tolist(),
            }
        )
    result: dict[str, Any] = {
        "scene": scene.name,
        "horizon": scene.horizon,
        "n_states": len(mu0),
        "error": max(max(r["error"]) for r in per_h),
        "energy": max(max(r["energy"]) for r in per_h),
        "casimir": max(max(r["casimir"]) for r in per_h),
        "converged": all(all(r["converged"]) for r in per_h),
        "n_failed": sum(len(r["converged"]) - sum(r["converged"]) for r in per_h),
        "per_h": per_h,
    }
    result["target_met"] = meets_target(result, scene.target)
    return result


def _casimirs(system: PoissonSystem, mu: np.ndarray) -> np.ndarray:
    """The system's Casimirs at μ (..., n) → (..., m); zeros (m = 1) when none is known."""
    c = system.casimirs(mu)
    return np.zeros((*np.shape(mu)[:-1], 1)) if c is None else np.asarray(c)


def meets_target(result: Mapping[str, Any], target: Target | Scene) -> bool:
    """Whether an :func:`evaluate` result reaches every threshold the target sets."""
    if isinstance(target, Scene):
        target = target.target
    if target.error is not None and not result["error"] <= target.error:
        return False
    if target.energy is not None and not result["energy"] <= target.energy:
        return False
    return not (target.newton == "all" and not result["converged"])


def summary(result: Mapping[str, Any]) -> dict[str, Any]:
    """The headline numbers of an :func:`evaluate` result (no per-state lists)."""
    keys = ("error", "energy", "casimir", "converged", "n_failed", "target_met")
    return {k: result[k] for k in keys}


class TargetStop:
    """A ``train(stop=...)`` callback: exports the live model, rolls the scene out in Rust and
    asks to stop once the target is met. ``history`` keeps one :func:`summary` per call, with
    its ``iteration`` and the ``seconds`` the evaluation took."""

    def __init__(
        self, scene: Scene, cfg: TrainConfig, *, log: Callable[[str], None] | None = None
    ) -> None:
        self.scene = scene
        self.cfg = cfg
        self.log = log
        self.history: list[dict[str, Any]] = []

    def __call__(self, iteration: int, s_fn: GeneratingFunction) -> bool:
        from .train import export_bytes

        t0 = time.perf_counter()
        model = BisectionIntegrator(export_bytes(s_fn, self.cfg))
        row = {"iteration": iteration, **summary(evaluate(model, self.scene))}
        row["seconds"] = time.perf_counter() - t0
        self.history.append(row)
        if self.log is not None:
            self.log(
                f"[{self.scene.name}] iteration {iteration}: error {row['error']:.3e}, "
                f"max dH/H {row['energy']:.3e}, converged {row['converged']}, "
                f"target {'met' if row['target_met'] else 'not met'}"
            )
        return bool(row["target_met"])


def train_scene(
    path: str | Path,
    out: str | Path,
    *,
    progress: bool = True,
    command: str | None = None,
    name: str | None = None,
    overrides: Mapping[str, Any] | None = None,
    max_seconds: float | None = None,
    force: bool = False,
) -> Path | None:
    """Trains a model for the scene file ``path`` until its target is met on the scene's states
    (or the configured iterations run out) and writes it to ``out``.

    The configuration is :func:`derive_config` (the scene's [model], then ``overrides``, e.g.
    TrainConfig fields from the command line); every ``evaluate_every`` iterations the model is
    exported and rolled out (:class:`TargetStop`). The metadata records ``scene``,
    ``scene_target``, ``target_met``, ``scene_result`` (the exported model's :func:`summary`),
    ``iterations_run``, ``stopped_early`` and ``command`` (default:
    ``poisson-rs train --scene PATH --out OUT``); ``name`` defaults to the stem of ``out``.
    ``progress`` shows a progress bar and prints one line per evaluation, and the scene error of
    the Taylor terms alone (no network) before and after. ``max_seconds`` ends training after that
    wall time (see :func:`~poisson_rs.train.train`). Returns ``out``.

    When the Taylor terms alone (no network) already meet the scene's target, training would
    only add cost: it says so and returns None without training or writing, unless ``force``.
    """
    from .files import check_output_path
    from .train import export_bytes, save_result, train

    check_output_path(out)
    scene = load_scene(path)
    cfg = derive_config(scene, **dict(overrides or {}))
    cfg.validate()
    baseline = summary(evaluate(BisectionIntegrator(export_bytes(_bare(cfg), cfg)), scene))
    if progress:
        print(
            f"scene {scene.name}: baseline, the Taylor terms alone (K = {cfg.taylor_order}): "
            f"error {baseline['error']:.3e}, max dH/H {baseline['energy']:.3e}"
        )
    if baseline["target_met"] and not force:
        chart = cfg.chart
        print(
            f"scene {scene.name}: the Taylor terms alone (K = {cfg.taylor_order}, {chart} chart) "
            f"already meet the target {scene.target.as_dict()}: no training needed. Use "
            f"taylor_integrator(system, {cfg.taylor_order}, {chart!r}), or give --force to "
            "train a model anyway; nothing written"
        )
        return None
    log: Callable[[str], None] | None = None
    if progress:
        from tqdm.auto import tqdm

        log = tqdm.write
    stopper = TargetStop(scene, cfg, log=log)
    result = train(
        cfg,
        progress=progress,
        evaluate_every=scene.evaluate_every,
        stop=stopper,
        max_seconds=max_seconds,
    )
    # Measured on the exported float64 model: exactly the file that is written.
    final = evaluate(BisectionIntegrator(export_bytes(result.model, cfg)), scene)
    if command is None:
        command = shlex.join(["poisson-rs", "train", "--scene", str(path), "--out", str(out)])
    extra = {
        "scene": scene.name,
        "scene_target": scene.target.as_dict(),
        "scene_steps": {"h": list(scene.h), "horizon": scene.horizon},
        "target_met": bool(final["target_met"]),
        "scene_result": summary(final),
        "iterations_run": result.iterations_run,
        "stopped_early": result.stopped_early,
        "evaluations": len(stopper.history),
        "scene_baseline": baseline,
    }
    saved = save_result(result, out, name=name or Path(out).stem, command=command, extra=extra)
    if progress:
        verdict = "met" if final["target_met"] else "NOT met"
        print(
            f"scene {scene.name}: target {verdict} after {result.iterations_run} iterations "
            f"({result.seconds:.1f} s): error {final['error']:.3e}, max dH/H "
            f"{final['energy']:.3e}, converged {final['converged']} (Taylor terms alone: error "
            f"{baseline['error']:.3e}) -> {saved}"
        )
    return saved


def _bare(cfg: TrainConfig) -> GeneratingFunction:
    """The configuration's generating function with the network's output zeroed: its exact
    Taylor terms alone, in the same file format (domain, h_max) as the trained model."""
    from .train import _zero_output, build_model

    s_fn = build_model(cfg)
    _zero_output(s_fn)
    return s_fn
