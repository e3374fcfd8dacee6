"""Type stubs for the Rust extension module."""

from os import PathLike

import numpy as np
import numpy.typing as npt

MODEL_FORMAT: str
__version__: str

class Model:
    """A generating function loaded from a model file (validated on load)."""

    @staticmethod
    def load(path: str | PathLike[str]) -> Model: ...
    @staticmethod
    def from_bytes(data: bytes) -> Model: ...
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
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
    def time_derivative(
        self, t: float, p: npt.NDArray[np.float64]
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...

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
    """Trajectories (n, n_steps // every + 1, 3) and per-trajectory diagnostics (n,).

    ``simplified``: batched steps (``model.batch > 1``) reuse the Newton Jacobian while the
    updates contract fast enough; the result agrees with full Newton to ``tol``.

    Runs in segments of about 50 ms with the GIL released, checking for signals in between
    (Ctrl-C raises KeyboardInterrupt); the result does not depend on the segmentation. An output
    over 16 GiB, or one that cannot be allocated, raises MemoryError before any step.
    """

def rollout_classical(
    name: str,
    inertia: tuple[float, float, float],
    mu0: npt.NDArray[np.float64],
    h: float,
    n_steps: int,
    every: int = 1,
    tol: float = 1e-12,
    max_iter: int = 50,
) -> tuple[npt.NDArray[np.float64], dict[str, npt.NDArray[np.generic]]]:
    """As :func:`rollout_model`, for the classical method ``name``."""
