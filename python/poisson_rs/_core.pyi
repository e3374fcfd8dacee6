"""Type stubs for the Rust extension module."""

from os import PathLike
from typing import Any, TypeAlias, final

import numpy as np
import numpy.typing as npt

__all__ = [
    "MAX_DIM",
    "MODEL_FORMAT",
    "LearnedModel",
    "Model",
    "RolloutDiagnostics",
    "__version__",
    "_after_fork_in_child",
    "exp_in_place",
    "expression_jets",
    "hamiltonian_field",
    "log_in_place",
    "rollout_classical",
    "rollout_hamiltonian_field",
    "rollout_jets_lie",
    "rollout_jets_polynomial",
    "rollout_lie_poisson",
    "rollout_log_canonical",
    "rollout_log_classical",
    "rollout_model",
    "rollout_polynomial_field",
    "rollout_polynomial_realization",
    "serial_rollouts",
    "step_angles",
    "usable_memory",
]

MODEL_FORMAT: str
MAX_DIM: int
# A field program: (code, a, b, c, outputs).
_FieldProgram: TypeAlias = tuple[
    npt.NDArray[np.int64],
    npt.NDArray[np.int64],
    npt.NDArray[np.int64],
    npt.NDArray[np.float64],
    npt.NDArray[np.int64],
]
# H as a sum over distances: (radial, weight, power, dims, first, second, coeffs, exponents).
_DistanceTable: TypeAlias = tuple[
    npt.NDArray[np.int64],
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
    npt.NDArray[np.int64],
    npt.NDArray[np.int64],
    npt.NDArray[np.int64],
    npt.NDArray[np.float64],
    npt.NDArray[np.int64],
]

__version__: str

def _after_fork_in_child() -> None:
    """Marks this process as a forked child: its rollouts run serially from now on."""

def serial_rollouts() -> bool:
    """Whether rollouts in this process run serially (a forked child)."""

@final
class RolloutDiagnostics:
    """A rollout's per-trajectory diagnostics, kept in the core until asked for."""

    def summary(self) -> tuple[int, int, int, int, float, int]:
        """(n_failed, first failed trajectory or -1, its failed step, its failure code, the
        largest step angle ignoring NaN (NaN if none), its index or -1)."""
    def arrays(self) -> dict[str, npt.NDArray[np.generic]]:
        """The diagnostics as a dict of (n,) arrays (the fields of ``RolloutInfo`` but
        ``out_of_domain``)."""
    def __len__(self) -> int: ...

@final
class Model:
    """A generating function loaded from a model file (validated on load)."""

    @staticmethod
    def load(path: str | PathLike[str]) -> Model:
        """FileNotFoundError, ValueError for a malformed file, MemoryError where its layers do
        not fit (each weight is held about four times: read, packed, transposed, packed)."""
    @staticmethod
    def from_bytes(data: bytes) -> Model:
        """As :meth:`load`, from the file's bytes (borrowed, not copied)."""
    @property
    def dim(self) -> int:
        """Dimension N of the model's Lie algebra (3 for the rigid body)."""
    @property
    def structure_constants(self) -> npt.NDArray[np.float64]:
        """c[i, j, k] of the model's algebra, shape (N, N, N)."""
    @property
    def metadata(self) -> dict[str, str]: ...
    @property
    def chart(self) -> str: ...
    @property
    def mlp_power(self) -> int: ...
    @property
    def widths(self) -> list[int]: ...
    @property
    def n_parameters(self) -> int: ...
    @property
    def batch(self) -> int:
        """Trajectories a rollout solves together in batched passes (1: one at a time)."""
    @property
    def n_polynomial_terms(self) -> int: ...
    def derivatives(
        self, t: float, p: npt.NDArray[np.float64]
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """S (n,), ∂S/∂p (n, N), ∂²S/∂p² (n, N, N) at time t. MemoryError, before anything is
        allocated, where the outputs and the evaluation workspace (which grows with the widest
        layer) exceed what this process may use: the least of MemAvailable, the address-space
        limit (RLIMIT_AS) and the cgroup's memory limit."""
    def time_derivative(
        self, t: float, p: npt.NDArray[np.float64]
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """S (n,) and ∂S/∂t (n,) at time t; MemoryError as for :meth:`derivatives`."""

@final
class LearnedModel:
    """A learned generating function S(t, x) = exact Taylor-HJ terms + t^m · MLP(t, x) on a
    realization, stepped by full Newton on tar(∇S(h, x), x) = x_k, then sou
    (|δ|∞ ≤ tol · max(|x|∞, 1)). One class for every realization: the log-canonical groupoid
    (x is q = ln x there; every monomial Casimir kept to round-off) and the order-n realization
    of a polynomial bivector."""

    @staticmethod
    def from_log_canonical_bytes(data: bytes) -> LearnedModel:
        """The bytes of a log-canonical model file (metadata ``structure = log_canonical``).
        ValueError for a malformed file or one of another structure."""
    @staticmethod
    def from_polynomial_tables(
        sou_index: npt.NDArray[np.int64],
        sou_coeffs: npt.NDArray[np.float64],
        sou_exponents: npt.NDArray[np.int64],
        tar_index: npt.NDArray[np.int64],
        tar_coeffs: npt.NDArray[np.float64],
        tar_exponents: npt.NDArray[np.int64],
        s_coeffs: npt.NDArray[np.float64],
        s_exponents: npt.NDArray[np.int64],
        weights: list[npt.NDArray[np.float64]],
        biases: list[npt.NDArray[np.float64]],
        mlp_power: int,
    ) -> LearnedModel:
        """β (sou) and α (tar) as term tables over (p, x) as for
        :func:`rollout_polynomial_realization`, S's Taylor part over (t, x); ``weights[i]``
        (out, in), ``biases[i]`` (out,), inputs (t, x), tanh between layers (empty lists: no
        network). ValueError for a malformed table or network."""
    @property
    def realization(self) -> str:
        """ "log_canonical" or "polynomial"."""
    @property
    def dim(self) -> int: ...
    @property
    def metadata(self) -> dict[str, str]:
        """The model file's metadata (empty for a model built from tables)."""
    @property
    def mlp_power(self) -> int: ...
    @property
    def n_parameters(self) -> int: ...
    @property
    def n_taylor_terms(self) -> int: ...
    def derivatives(
        self, t: float, x: npt.NDArray[np.float64]
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """S (n,), ∂S/∂x (n, N), ∂²S/∂x² (n, N, N) at time t in the realization's base
        coordinates, exact (forward-mode duals)."""
    def rollout(
        self,
        x0: npt.NDArray[np.float64],
        h: float,
        n_steps: int,
        every: int = 1,
        tol: float = 1e-12,
        max_iter: int = 50,
    ) -> tuple[npt.NDArray[np.float64], dict[str, npt.NDArray[np.generic]]]:
        """Trajectories (n, n_steps // every + 1, N) in the realization's base coordinates and
        per-trajectory diagnostics (n,); ``x0`` finite (ValueError naming the state)."""

def rollout_model(
    model: Model,
    mu0: npt.NDArray[np.float64],
    h: float,
    n_steps: int,
    every: int = 1,
    tol: float = 1e-12,
    max_iter: int = 50,
    simplified: bool = True,
) -> tuple[npt.NDArray[np.float64], dict[str, npt.NDArray[np.generic]]]:
    """Trajectories (n, n_steps // every + 1, N) and per-trajectory diagnostics (n,).

    ``simplified``: batched steps (``model.batch > 1``) reuse the Newton Jacobian while the
    updates contract fast enough; the result agrees with full Newton to ``tol``.

    Runs in segments of about 50 ms with the GIL released, checking for signals in between
    (Ctrl-C raises KeyboardInterrupt); the result does not depend on the segmentation. An output
    that, with every thread's workspace, does not fit in the memory this process may use (the
    least of MemAvailable, RLIMIT_AS and the cgroup's limit), or that cannot be allocated,
    raises MemoryError before any step. In a forked child the rollout runs serially.
    """

def rollout_classical(
    name: str,
    inertia: tuple[float, float, float],
    mu0: npt.NDArray[np.float64] | list[Any],
    h: float,
    n_steps: int,
    every: int = 1,
    tol: float = 1e-12,
    max_iter: int = 50,
    lazy: bool = False,
) -> tuple[npt.NDArray[np.float64], Any] | None:
    """As :func:`rollout_model`, for the classical method ``name``; ``lazy=True`` returns a
    :class:`RolloutDiagnostics` in place of the dict. A state holding NaN or ±∞ is a
    ValueError. ``mu0`` may also be a list of 3 plain numbers (float, or int within int64):
    one state, read without NumPy; None for any other list."""

def rollout_lie_poisson(
    name: str,
    c: npt.NDArray[np.float64],
    powers: npt.NDArray[np.int64],
    coeffs: npt.NDArray[np.float64],
    mu0: npt.NDArray[np.float64] | list[Any],
    h: float,
    n_steps: int,
    every: int = 1,
    tol: float = 1e-12,
    max_iter: int = 50,
    heavy_top: tuple[tuple[float, float, float], float, tuple[float, float, float]] | None = None,
    lazy: bool = False,
) -> tuple[npt.NDArray[np.float64], Any] | None:
    """As :func:`rollout_classical`, for the Lie–Poisson system with structure constants ``c``
    (N, N, N) and Hamiltonian Σ coeffs[m] Π μ_i^powers[m, i]: "rk4", "midpoint", or "splitting"
    with ``heavy_top`` = (inertia, mgl, com)."""

def log_in_place(x: npt.NDArray[np.float64]) -> None:
    """x ← ln x elementwise, in place, by libm (C-contiguous float64, any shape): the same bits
    on every CPU, where NumPy's log dispatches on it."""

def exp_in_place(q: npt.NDArray[np.float64]) -> None:
    """q ← e^q elementwise, in place, by libm (C-contiguous float64, any shape): the same bits
    on every CPU, where NumPy's exp dispatches on it."""

def rollout_log_canonical(
    c: npt.NDArray[np.float64],
    t_powers: npt.NDArray[np.int64],
    exponents: npt.NDArray[np.int64],
    coeffs: npt.NDArray[np.float64],
    linear: npt.NDArray[np.float64],
    q0: npt.NDArray[np.float64],
    h: float,
    n_steps: int,
    every: int = 1,
    tol: float = 1e-12,
    max_iter: int = 50,
) -> tuple[npt.NDArray[np.float64], dict[str, npt.NDArray[np.generic]]]:
    """Bisection rollout on the log-canonical groupoid of ``c`` (N, N), in q = ln x, of
    S(t, q) = Σ_m coeffs[m] t^t_powers[m] e^{exponents[m]·q} + t·linear·q: solve
    q + ½ c ∇S(q) = q_k, then q_{k+1} = q − ½ c ∇S(q). q0 (n, N) → (n, n_steps // every + 1, N)
    in q, and the per-trajectory dict. A step whose e^q leaves the float64 orthant fails
    (code 5 or 3)."""

def rollout_log_classical(
    name: str,
    c: npt.NDArray[np.float64],
    powers: npt.NDArray[np.int64],
    coeffs: npt.NDArray[np.float64],
    b: npt.NDArray[np.float64],
    s0: npt.NDArray[np.float64],
    h: float,
    n_steps: int,
    every: int = 1,
    tol: float = 1e-12,
    max_iter: int = 50,
) -> tuple[npt.NDArray[np.float64], dict[str, npt.NDArray[np.generic]]]:
    """Classical rollout of the log-canonical system c, H = Σ coeffs[m] x^powers[m] − Σ b_i ln x_i:
    "rk4", "midpoint" (state x; leaving the orthant fails with code 5), "log_splitting",
    "log_splitting4" (state q = ln x; exact one-variable flows, Strang / Suzuki)."""

def rollout_polynomial_field(
    name: str,
    index: npt.NDArray[np.int64],
    coeffs: npt.NDArray[np.float64],
    exponents: npt.NDArray[np.int64],
    x0: npt.NDArray[np.float64],
    h: float,
    n_steps: int,
    every: int = 1,
    tol: float = 1e-13,
    max_iter: int = 50,
) -> tuple[npt.NDArray[np.float64], dict[str, npt.NDArray[np.generic]]]:
    """A classical baseline ("rk4" or "midpoint") of the polynomial vector field
    ẋ_i = f_i(x), its components as one term table (index (M,): the component; exponents
    (M, N)), from each row of x0 (n, N), in SIMD lanes."""

def rollout_polynomial_realization(
    sou_index: npt.NDArray[np.int64],
    sou_coeffs: npt.NDArray[np.float64],
    sou_exponents: npt.NDArray[np.int64],
    tar_index: npt.NDArray[np.int64],
    tar_coeffs: npt.NDArray[np.float64],
    tar_exponents: npt.NDArray[np.int64],
    s_coeffs: npt.NDArray[np.float64],
    s_exponents: npt.NDArray[np.int64],
    x0: npt.NDArray[np.float64],
    h: float,
    n_steps: int,
    every: int = 1,
    tol: float = 1e-13,
    max_iter: int = 50,
) -> tuple[npt.NDArray[np.float64], dict[str, npt.NDArray[np.generic]]]:
    """Taylor-HJ on an approximate realization of a polynomial bivector, from each row of x0
    (n, N): β (sou) and α (tar) as term tables over (p, x) (index (M,): the component;
    exponents (M, 2N)), S(t, x) as one over (t, x) (exponents (K, N + 1)). A step solves
    α(∇S(h, x), x) = x_k by Newton and returns β(∇S(h, x), x)."""

def step_angles(
    c: npt.NDArray[np.float64],
    powers: npt.NDArray[np.int64],
    coeffs: npt.NDArray[np.float64],
    mu: npt.NDArray[np.float64],
    h: float,
) -> npt.NDArray[np.float64]:
    """h × max(‖ad_∇H(μ)‖_F/√2, ‖∂f/∂μ‖_F) at each row of ``mu`` (n, N) for the Lie–Poisson system
    (c, powers, coeffs): the angle (rad) a step of size h turns each state by. Shape (n,)."""

def expression_jets(
    code: npt.NDArray[np.int64],
    a: npt.NDArray[np.int64],
    b: npt.NDArray[np.int64],
    c: npt.NDArray[np.float64],
    x: npt.NDArray[np.float64],
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
def hamiltonian_field(
    code: npt.NDArray[np.int64],
    a: npt.NDArray[np.int64],
    b: npt.NDArray[np.int64],
    c: npt.NDArray[np.float64],
    upper_index: npt.NDArray[np.int64],
    upper_coeffs: npt.NDArray[np.float64],
    upper_exponents: npt.NDArray[np.int64],
    x: npt.NDArray[np.float64],
    program: _FieldProgram | None = None,
    distances: _DistanceTable | None = None,
) -> npt.NDArray[np.float64]: ...
def rollout_hamiltonian_field(
    name: str,
    code: npt.NDArray[np.int64],
    a: npt.NDArray[np.int64],
    b: npt.NDArray[np.int64],
    c: npt.NDArray[np.float64],
    upper_index: npt.NDArray[np.int64],
    upper_coeffs: npt.NDArray[np.float64],
    upper_exponents: npt.NDArray[np.int64],
    x0: npt.NDArray[np.float64],
    h: float,
    n_steps: int,
    every: int = 1,
    tol: float = 1e-13,
    max_iter: int = 50,
    program: _FieldProgram | None = None,
    distances: _DistanceTable | None = None,
) -> tuple[npt.NDArray[np.float64], dict[str, npt.NDArray[np.generic]]]: ...
def rollout_jets_polynomial(
    code: npt.NDArray[np.int64],
    a: npt.NDArray[np.int64],
    b: npt.NDArray[np.int64],
    c: npt.NDArray[np.float64],
    hamiltonian_vars: int,
    order: int,
    sou_index: npt.NDArray[np.int64],
    sou_coeffs: npt.NDArray[np.float64],
    sou_exponents: npt.NDArray[np.int64],
    tar_index: npt.NDArray[np.int64],
    tar_coeffs: npt.NDArray[np.float64],
    tar_exponents: npt.NDArray[np.int64],
    x0: npt.NDArray[np.float64],
    h: float,
    n_steps: int,
    every: int = 1,
    tol: float = 1e-13,
    max_iter: int = 50,
) -> tuple[npt.NDArray[np.float64], dict[str, npt.NDArray[np.generic]]]: ...
def rollout_jets_lie(
    code: npt.NDArray[np.int64],
    a: npt.NDArray[np.int64],
    b: npt.NDArray[np.int64],
    c: npt.NDArray[np.float64],
    hamiltonian_vars: int,
    order: int,
    c_lie: npt.NDArray[np.float64],
    x0: npt.NDArray[np.float64],
    h: float,
    n_steps: int,
    every: int = 1,
    tol: float = 1e-13,
    max_iter: int = 50,
) -> tuple[npt.NDArray[np.float64], dict[str, npt.NDArray[np.generic]]]: ...
def usable_memory() -> int | None: ...
