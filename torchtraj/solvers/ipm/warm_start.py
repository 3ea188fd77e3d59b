r"""The interior-point iteration started from given multipliers (``tt.solve``'s ``duals``), as IPOPT's
``warm_start_init_point``: a solve near an earlier one, or a controller's step from the previous step, shifted.

Given, per instance, the multipliers of the inequality rows :math:`\bar z` and of the equality rows
:math:`\bar\nu` (per block, as :attr:`~torchtraj.Solution.multipliers` holds them), optionally the costates
:math:`\bar\lambda` (:attr:`~torchtraj.Solution.costate`) and a barrier parameter :math:`\bar\mu`, all in the units
of the problem as given, the iteration on the scaled problem (objective factor :math:`s_f`,
:mod:`~torchtraj.solvers.ipm.scaling`, whose multipliers are :math:`s_f` times the problem's) starts at

.. math::

    z = \max(s_f \bar z,\ \kappa_z) \text{ on the rows that apply},\quad y = z,\quad
    \lambda = s_f \bar\lambda,\quad \nu = s_f \bar\nu,\quad s = \max(-g,\ \kappa_1),\quad
    \mu_0 = \min\big(\mu_{init},\ \max(s_f \bar\mu,\ \mu_{min})\big),

with :math:`\kappa_z` = ``IPOptions.warm_start_mult_bound_push`` (IPOPT's ``warm_start_mult_bound_push``,
1e-3), :math:`\kappa_1` the cold start's ``bound_push``, :math:`\mu_{min}` = ``IPOptions.warm_start_barrier_min``
and :math:`\mu_{init}` = ``barrier_initial``. Missing blocks and costates start at zero. ``y = z`` is their
relation at a KKT point (the slack's stationarity row). The least-squares estimate of the multipliers
(:mod:`~torchtraj.solvers.ipm.initialization`) is made for the cold instances alone.

- **The slacks** start from the rows at the given states, as a cold start's do (IPOPT's ``warm_start_bound_push``
  on the given point): a controller's car observes other obstacles from step to step, so the last step's slacks
  belong to other rows.
- **The barrier.** Without a ``"barrier"`` entry every instance starts warm at :math:`\mu_{init}` (IPOPT keeps
  ``mu_init``). With one, an instance whose :math:`\bar\mu` is 0 starts cold, as a solve without ``duals`` does
  (a controller's instance that restarted: its carried duals are zeros); the others start at :math:`\mu_0` above.
  :math:`\mu_{min}` keeps a step from starting at the small barrier where the previous one ended while the
  measured state has moved the problem (the floor's effect on the controllers: ``docs/benchmarks.md``, MPC).
- **With the primal point they belong to.** The duals of one point given with another start mislead the
  iteration: car_3obs from its default start (the rollout of its controls, through the obstacles) with the duals of
  its optimum ends ``LOCALLY_INFEASIBLE`` after 21 iterations, where the cold solve converges. Pass the solution's
  ``U0`` and ``X0`` with its duals (a controller passes the shifted plan).
- **A branch of local optima.** From a solution's point, the iteration follows that solution's local optimum as
  the problem moves; a cold solve of the moved problem may reach another, lower or higher (``docs/benchmarks.md``,
  MPC, has examples).
- **Units.** :attr:`Solution.multipliers`, :attr:`Solution.costate` and the history's ``barrier`` are in the
  units of the problem as given; the factor :math:`s_f` of this solve's start converts them, so that a warm
  start is the same whatever the two solves' factors.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import torch
from torch import Tensor

from ...core.constraints import Constraints, stack_blocks
from ...core.masks import RowPicker
from .iterate import Hooks, Iterate
from .options import IPOptions


def warm_start_hooks(cons: Constraints, duals: Optional[dict], scale: Optional[Tensor], B: int, like: Tensor,
                     opts: IPOptions) -> Optional[Hooks]:
    """The :class:`~torchtraj.solvers.ipm.iterate.Hooks` that start the iteration from ``duals`` (module
    docstring), for a batch of ``B`` instances whose objective factor is ``scale (B,)`` (``None``: 1); ``None``
    without ``duals``. ``like``: a tensor of the batch's dtype and device."""
    if duals is None:
        return None

    def entry(name: str) -> Optional[Tensor]:
        value = duals.get(name)
        return None if value is None else torch.as_tensor(value, dtype=like.dtype, device=like.device)

    barrier, lam = entry("barrier"), entry("costate")
    warm = None if barrier is None else barrier.expand(B) > 0
    stage, terminal = stack_blocks(cons, duals.get("multipliers") or {}, 0.0, like.new_zeros(B))
    if scale is not None:  # into the scaled problem's units
        per_knot, per_row = scale.reshape(B, 1, 1), scale.reshape(B, 1)
        stage, terminal = per_knot * stage, per_row * terminal
        lam = None if lam is None else per_knot * lam
        barrier = None if barrier is None else scale * barrier
    knots = cons.ineq_knot_mask
    push = opts.warm_start_mult_bound_push

    def start(it: Iterate) -> Iterate:
        z = torch.clamp(stage[..., :cons.mi], min=push) * knots
        zN = torch.clamp(terminal[..., :cons.miN], min=push)
        values = {"z": z, "zN": zN, "y": z.clone(), "yN": zN.clone(), "nu": stage[..., cons.mi:],
                  "nuN": terminal[..., cons.miN:]}
        if lam is not None:
            values["lam"] = lam.expand_as(it.lam)
        if warm is not None:  # the cold instances keep the cold start's values
            pick = RowPicker(warm)
            values = {name: pick(value, getattr(it, name)) for name, value in values.items()}
        return dataclasses.replace(it, **values)

    cold_barrier = like.new_full((B,), opts.barrier_initial)
    if warm is None:  # every instance warm: none takes the least-squares estimate
        return Hooks(start=start, barrier=cold_barrier)
    mu = torch.where(warm, torch.clamp(barrier, min=opts.warm_start_barrier_min, max=opts.barrier_initial),
                     cold_barrier)
    return Hooks(start=start, barrier=mu, estimate=~warm)
