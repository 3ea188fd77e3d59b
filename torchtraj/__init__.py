"""torchtraj: batched, differentiable trajectory optimisation in PyTorch."""

from .altro import ALTROOptions
from .ilqr import ILQROptions
from .interior_point import IPOptions
from .projection import ProjectionOptions
from .integrators import euler, rk4
from .mpc import MPC
from .problem import Problem
from .solution import History, Solution
from .solve import Method, solve
from .status import Status
from .time_penalty import TimePenalized, time_penalized

__all__ = ["ALTROOptions", "History", "ILQROptions", "IPOptions", "MPC", "ProjectionOptions", "Method", "Problem", "Solution", "Status", "TimePenalized", "euler", "rk4", "solve", "time_penalized"]
__version__ = "0.1.0"


def __getattr__(name):
    # the model zoo and the problem set are imported on first use
    if name in ("models", "problems"):
        import importlib

        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'torchtraj' has no attribute {name!r}")
