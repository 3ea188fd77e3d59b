"""Globalisation shared by the solvers: how a Newton or Riccati step is made safe far from a solution.

A solver is a step (its KKT model, solved by :mod:`torchtraj.riccati`) and a globalisation. The pieces here are
written once and used by every solver that needs them; none imports a solver:

* :mod:`~torchtraj.globalization.line_search`: the batched backtracking driver (rounds of step sizes, the first
  accepted one per instance); the acceptance test (iLQR's ratio test, the IPM's filter, ALTRO's projection's
  decrease of the violation) is the caller's.
* :mod:`~torchtraj.globalization.filter`: the per-instance filter of the interior-point method's line search.
* :mod:`~torchtraj.globalization.regularization`: the regularisation schedules, ALTRO's ``ρ`` and IPOPT's inertia
  correction.
"""

from .filter import Filter
from .line_search import Accepted, backtrack
from .regularization import inertia_correction, rho_schedule

__all__ = ["Accepted", "Filter", "backtrack", "inertia_correction", "rho_schedule"]
