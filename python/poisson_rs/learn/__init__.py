"""Learning Poisson integrators from trajectories: :func:`learn` (see :mod:`.api`)."""

from .api import MODES, learn
from .data import CasimirDriftWarning, HullWarning, TrajectoryData, load_trajectories, prepare
from .discover import NotExplainedWarning
from .fixed_step import FixedStepIntegrator
from .report import Candidate, LearnReport

__all__ = [
    "MODES",
    "Candidate",
    "CasimirDriftWarning",
    "FixedStepIntegrator",
    "HullWarning",
    "LearnReport",
    "NotExplainedWarning",
    "TrajectoryData",
    "learn",
    "load_trajectories",
    "prepare",
]
