"""Implicit differentiation of solutions, by the names the rest of the library and its users import.

The layer is split by what each part computes: :mod:`~torchtraj.differentiation.kkt_system` (the KKT system at a
solution with its active rows held, its multipliers, dependent rows), :mod:`~torchtraj.differentiation.refine`
(Newton refinement onto the KKT point), :mod:`~torchtraj.differentiation.adjoint` (the backward solve and the
parameters' products) and :mod:`~torchtraj.differentiation.layer` (the autograd function, the modes and the
zero-gradient policy). Each opens with its mathematics.
"""

# the graphed kernels (:func:`torchtraj.core.graphs.graphed` keys its graphs by function), for their tests
from .adjoint import _adjoint, backward_solve, parameter_gradients  # noqa: F401
from .kkt_system import (
    KKTSystem,
    Multipliers,
    Rows,
    active_rows,
    default_active_tolerance,
    dependent_rows,
    kkt_system,
    rows_at,
)
from .layer import (
    GRADIENT_MODES,
    FirstOrderOnly,
    ImplicitSolution,
    attach_gradients,
    check_gradients_mode,
    masked_cost,
    requires_gradients,
)
from .refine import Refined, _newton_step, default_stationarity_tolerance, refine  # noqa: F401

__all__ = ["GRADIENT_MODES", "FirstOrderOnly", "ImplicitSolution", "KKTSystem", "Multipliers", "Refined", "Rows",
           "active_rows", "attach_gradients", "backward_solve", "check_gradients_mode",
           "default_active_tolerance", "default_stationarity_tolerance", "dependent_rows", "kkt_system", "masked_cost",
           "parameter_gradients", "refine", "requires_gradients", "rows_at"]
