"""The linear-quadratic (KKT) model of a problem at a point, shared by every solver and the implicit layer.

* :mod:`~torchtraj.kkt.model`: the objective and its LQR model (iLQR's);
* :mod:`~torchtraj.kkt.activity`: the rules that decide which inequality rows a Newton step holds;
* :mod:`~torchtraj.kkt.newton`: the KKT system with those rows held, as the Riccati core's LQR, and its step;
* :mod:`~torchtraj.kkt.merit`: the largest violation, dynamics defects included.
"""

from .merit import largest_violation
from .model import cost_model, total_cost
from .newton import NewtonStep, held_lqr, newton_rhs, newton_step, without_offsets

__all__ = ["NewtonStep", "cost_model", "held_lqr", "largest_violation", "newton_rhs", "newton_step", "total_cost",
           "without_offsets"]
