"""torchtraj: batched, differentiable trajectory optimisation in PyTorch."""

from .integrators import euler, rk4
from .problem import Problem

__all__ = ["Problem", "euler", "rk4"]
__version__ = "0.1.0"
