"""The first-order optimality check of a returned solution, shared by the solver tests."""

import torch

import torchtraj as tt
import torchtraj.kkt
from torchtraj.core.batching import map_stage
from torchtraj.core.constraints import Constraints


def kkt_residuals(problem, sol):
    """Stationarity ``|∇_{X[1:],U} L|∞ / max(1, |multipliers|∞)`` (scaled like IPOPT's dual infeasibility) of
    ``L = J + Σ λ_{k+1}ᵀ (f(x_k, u_k) − x_{k+1}) + Σ zᵀ g + νᵀ h`` with the solution's costates and multipliers,
    the most negative inequality multiplier and the largest complementarity product ``|z g|`` over the rows
    that apply."""
    c = Constraints(problem)
    params = problem.batched_params(sol.X.shape[0])
    X = sol.X.detach().clone().requires_grad_(True)
    U = sol.U.detach().clone().requires_grad_(True)
    lam, m = sol.costate, sol.multipliers
    L = tt.kkt.total_cost(problem, X, U, params).sum()
    L = L + (lam[:, 1:] * (map_stage(problem.dynamics, X[:, :-1], U, params) - X[:, 1:])).sum()
    values = c.evaluate(X, U, params)
    products = [torch.zeros(1, dtype=X.dtype)]
    duals = [torch.zeros(1, dtype=X.dtype)]
    if c.mi:
        z = torch.cat([m[k] for k in c.ineq_blocks if c.ineq_blocks[k].stop > c.ineq_blocks[k].start], -1)
        on = c.ineq_knot_mask > 0
        g = torch.where(on, values.ineq, torch.zeros_like(values.ineq))
        L = L + (z * g).sum()
        products.append((z * g).detach()[:, on].abs().flatten())
        duals.append(z[:, on].flatten())
    if c.miN:
        L = L + (m["terminal_ineq"] * values.ineqN).sum()
        products.append((m["terminal_ineq"] * values.ineqN).detach().abs().flatten())
        duals.append(m["terminal_ineq"].flatten())
    if c.me:
        L = L + (m["stage_eq"] * values.eq).sum()
    if c.meN:
        L = L + (m["terminal_eq"] * values.eqN).sum()
    gx, gu = torch.autograd.grad(L, (X, U))
    scale = max(1.0, float(lam.abs().max()), *(float(v.abs().max()) for v in m.values() if v.numel()))
    stationarity = max(float(gx[:, 1:].abs().max()), float(gu.abs().max())) / scale
    return stationarity, float(torch.cat(duals).min()), float(torch.cat(products).max())
