"""torchtraj: batched, differentiable trajectory optimisation in PyTorch."""

from .control.mpc import MPC
from .core.problem import Problem
from .core.solution import History, Solution
from .core.status import Status
from .integrators import euler, rk4
from .iterations.ilqr import ILQROptions
from .solve import Method, solve
from .solvers import Solver
from .solvers.altro.options import ALTROOptions
from .solvers.altro.projection import ProjectionOptions
from .solvers.eilqr.options import EILQROptions
from .solvers.hm_ilqr.options import HMILQROptions
from .solvers.ipm.options import IPOptions
from .time_penalty import TimePenalized, time_penalized

__all__ = ["ALTROOptions", "EILQROptions", "HMILQROptions", "History", "ILQROptions", "IPOptions", "MPC",
           "ProjectionOptions", "Method", "Problem", "Solution", "Solver", "Status", "TimePenalized", "euler", "rk4",
           "solve", "time_penalized"]
__version__ = "0.1.0"


def __getattr__(name):
    # the model zoo and the problem set are imported on first use
    if name in ("models", "problems"):
        import importlib

        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'torchtraj' has no attribute {name!r}")
