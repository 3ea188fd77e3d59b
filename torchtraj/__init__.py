"""torchtraj: batched, differentiable trajectory optimisation in PyTorch.

Start with :class:`Problem` (a problem written as per-instance functions), :func:`solve` (one batched solve; the
methods are listed by ``torchtraj.solvers.names()``) and :class:`MPC` (a receding-horizon controller). The problem
set is :mod:`torchtraj.problems`, the models :mod:`torchtraj.models`, the Gymnasium environments
:mod:`torchtraj.envs` (their ids, ``torchtraj/Pendulum-v0`` and others, are registered by ``import torchtraj``),
pictures of a solve (its convergence, its trajectories) :mod:`torchtraj.plotting`.
"""

from .control.mpc import MPC
from .core.problem import Problem
from .core.solution import History, Solution
from .core.status import Status
from .integrators import euler, rk4
from .iterations.ilqr import ILQROptions
from .minimum_time import MinimumTime, minimum_time
from .registration import register as _register_environments
from .solve import Method, solve, warm_start
from .solvers import Solver
from .solvers.altro.options import ALTROOptions
from .solvers.altro.projection import ProjectionOptions
from .solvers.eilqr.options import EILQROptions
from .solvers.hm_ilqr.options import HMILQROptions
from .solvers.ipm.options import IPOptions
from .time_penalty import TimePenalized, time_penalized

__all__ = ["ALTROOptions", "EILQROptions", "HMILQROptions", "History", "ILQROptions", "IPOptions", "MPC",
           "ProjectionOptions", "Method", "MinimumTime", "Problem", "Solution", "Solver", "Status", "TimePenalized",
           "euler", "minimum_time", "rk4", "solve", "time_penalized", "warm_start"]
__version__ = "0.1.0"

#: Submodules imported on first use (``tt.problems``, ...): they cost import time most programs do not need.
_LAZY = ("envs", "models", "plotting", "problems")

_register_environments()  # strings only: gymnasium imports torchtraj.envs when it makes one


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'torchtraj' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
