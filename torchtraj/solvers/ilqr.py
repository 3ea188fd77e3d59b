r"""iLQR for batches of unconstrained problems (method ``"ilqr"``; ALTRO §II-A).

The loop over iterations of :func:`torchtraj.iterations.ilqr.ilqr_step` (expansion, Riccati backward pass, batched
line search on the closed-loop rollouts, regularisation schedule: that module's docstring) until every instance
converged or failed, then the gains and costates at the solution. Constraints are ignored (reported in
``Solution.max_violation``): a converged solution is a KKT point of the unconstrained problem, which is what the
implicit layer differentiates (``handles_constraints = False`` of :class:`ILQR`).
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from ..core.batch import Batch
from ..core.compiled import kernel, rollout_kernel
from ..core.constraints import Constraints
from ..core.problem import Problem
from ..core.solution import History, Solution
from ..core.status import Status
from ..iterations.ilqr import CostObjective, ILQROptions, ilqr_step, log_iteration, start_status
from ..kkt.model import cost_model, total_cost
from ..riccati import LQR, LQRVectors, factorize
from .base import Solver


class ILQR(Solver):
    """Method ``"ilqr"``: :func:`solve_ilqr`. It simulates its states from ``x0`` (no state guess), carries no
    duals and ignores the constraints."""

    name = "ilqr"
    options_class = ILQROptions
    handles_constraints = False
    takes_state_guess = False
    takes_duals = False
    compiles = True

    def solve(self, problem: Problem, batch: Batch, options: ILQROptions) -> Solution:
        return solve_ilqr(problem, batch, options)


def solve_ilqr(problem: Problem, batch: Batch, options: Optional[ILQROptions] = None) -> Solution:
    """Solve the ``batch`` of instances of ``problem`` by iLQR, from ``x0 (B, nx)`` and controls ``U0 (B, N, nu)``
    with the parameters batched to B; constraints are ignored."""
    opts = options or ILQROptions()
    x0, U0, params = batch.x0, batch.U0, batch.params
    B = x0.shape[0]
    constraints = Constraints.of(problem)
    objective = CostObjective(problem)
    X = rollout_kernel(opts.compile)(problem.dynamics, x0, U0, params)
    U = U0
    J = kernel(total_cost, opts.compile)(problem, X, U, params)
    status = start_status(x0, X, J, opts)
    active = status == Status.RUNNING
    rho = torch.full((B,), opts.regularization_initial, dtype=x0.dtype, device=x0.device)
    drho = torch.zeros_like(rho)
    iterations = torch.zeros(B, dtype=torch.long, device=x0.device)
    rows = []
    stationarity = torch.zeros_like(rho)  # the last running iterate's: a stopped instance's history repeats it
    for it in range(opts.iterations):
        if not bool(active.any()):  # the only host synchronisation of an iteration
            break
        s = ilqr_step(problem, objective, params, x0, X, U, J, rho, drho, active, opts)
        X, U, J, rho, drho = s.X, s.U, s.J, s.rho, s.drho
        stationarity = torch.where(active, s.stationarity, stationarity)
        iterations = iterations + active.long()
        status = torch.where(s.converged, int(Status.CONVERGED), status)
        status = torch.where(s.blown, int(Status.MAX_REGULARIZATION), status)
        active = status == Status.RUNNING
        rows.append({
            "cost": J, "max_violation": constraints.max_violation(X, U, params),
            "step_size": s.alpha, "regularization": rho, "stationarity": stationarity,
        })
        if opts.verbose:
            log_iteration("ilqr", it, J, rho, active)
    status = torch.where(status == Status.RUNNING, int(Status.MAX_ITERATIONS), status)
    K, costate = kernel(_gains_and_costates, opts.compile)(problem, X, U, params, rho, opts.sweep)
    violation = constraints.max_violation(X, U, params)
    return Solution(
        X=X, U=U, K=K, cost=J, max_violation=violation, status=status, iterations=iterations,
        history=History.from_rows(rows), costate=costate, method="ilqr",
    )


def _gains_and_costates(problem: Problem, X: Tensor, U: Tensor, params, rho: Tensor, sweep: str = "sequential"):
    """Feedback gains (by the ``sweep`` of ``ILQROptions``) and costates at the solution."""
    lqr, rhs = cost_model(problem, X, U, params)
    return factorize(lqr, rho, sweep=sweep).K, _adjoint(lqr, rhs)


def _adjoint(lqr: LQR, rhs: LQRVectors) -> Tensor:
    """Costates of the unconstrained problem: ``λ_N = l_Nx``, ``λ_k = l_x + A_kᵀ λ_{k+1}``."""
    lam = rhs.qN
    lams = [lam]
    for k in range(lqr.A.shape[1] - 1, -1, -1):
        lam = rhs.q[:, k] + (lqr.A[:, k].transpose(-1, -2) @ lam.unsqueeze(-1)).squeeze(-1)
        lams.append(lam)
    return torch.stack(lams[::-1], 1)
