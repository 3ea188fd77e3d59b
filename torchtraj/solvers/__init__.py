"""The registry of methods: one :class:`~torchtraj.solvers.base.Solver` object per name.

``tt.solve``, :class:`~torchtraj.MPC` and the benchmarks find a method here by name and read its declarations
(:mod:`torchtraj.solvers.base`); none of them names a method. A new method is its own files and one
:func:`register` line below.
"""

from __future__ import annotations

from .altro import ALILQR, ALTRO
from .base import Solver
from .eilqr import EILQR
from .hm_ilqr import HMILQR
from .ilqr import ILQR
from .ipm import IPM

_REGISTRY: dict = {}


def register(solver: Solver) -> Solver:
    """Add ``solver`` under its ``name``; a name already taken is a ``ValueError``."""
    if not isinstance(solver, Solver):
        raise TypeError(f"solver must be a torchtraj.solvers.Solver, got {type(solver).__name__}")
    if solver.name in _REGISTRY:
        raise ValueError(f"method {solver.name!r} is already registered")
    _REGISTRY[solver.name] = solver
    return solver


def get(name) -> Solver:
    """The registered solver called ``name`` (a string, a :class:`~torchtraj.Method` or a :class:`Solver`, returned
    as it is); an unknown name is a ``ValueError`` listing the valid ones."""
    if isinstance(name, Solver):
        return name
    solver = _REGISTRY.get(getattr(name, "value", name)) if isinstance(name, str) else None
    if solver is None:
        raise ValueError(f"unknown method {name!r}; choose one of {names()}")
    return solver


def names() -> list:
    """The registered methods' names, in registration order."""
    return list(_REGISTRY)


# the order is that of `--method`'s choices in `python -m torchtraj.bench`
register(ILQR())
register(ALTRO())
register(ALILQR())
register(IPM())
register(HMILQR())
register(EILQR())

__all__ = ["ALILQR", "ALTRO", "EILQR", "HMILQR", "ILQR", "IPM", "Solver", "get", "names", "register"]
