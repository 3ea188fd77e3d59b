r"""Initial-state optimisation (Horizon eILQR §II-D): ``x_0`` as a decision variable, fixed by rows where wanted.

The Riccati core's backward sweep ends at stage 0 with the value function ``V_0(δx_0) = ½ δx_0ᵀ P_0 δx_0 + p_0ᵀ δx_0``
(the cost-to-go of the step along the computed policy) and the rows ``G_0 δx_0 + g_0 = 0`` that no control could
satisfy (the back-propagated constraints, §II-C; :attr:`~torchtraj.riccati.LQRSolution.g0`). With the initial rows
``E_0 δx_0 + e_0 = 0`` (the linearised ``h_0(x_0) = 0`` and, for a component ``i`` that stays given,
``x_{0,i} − x̄_{0,i} = 0``), the step's initial state solves the small KKT system (5) "evaluated at the initial
node"

.. math::

    \begin{bmatrix} P_0 & G_0^T & E_0^T \\ G_0 & 0 & 0 \\ E_0 & 0 & 0 \end{bmatrix}
    \begin{bmatrix} δx_0 \\ η_0 \\ μ_0 \end{bmatrix} = −\begin{bmatrix} p_0 \\ g_0 \\ e_0 \end{bmatrix},

after which the forward pass (§II-E) starts from ``δx_0`` and ``η_0`` (the core's ``initial_multiplier``): the
costate of the initial node is then ``λ_0 = P_0 δx_0 + p_0 + G_0ᵀ η_0 = −E_0ᵀ μ_0``, the stationarity of a free
``x_0``. Rows of ``G_0`` the back-propagation dropped (below its rank tolerance) are held at ``η = 0`` by a ``−1``
on the diagonal; rows that depend on each other (a fixed component that a goal also pins) are solved in the least-
squares sense, by the eigendecomposition of the symmetric system, which also gives its inertia: the reduced
Hessian ``Zᵀ P_0 Z`` is positive definite exactly where the system has ``n_x`` positive eigenvalues.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Union

import torch
from torch import Tensor
from torch.func import jacrev

from ...core.batching import map_state
from ...core.derivatives import terminal_jacobian
from ...riccati import LQRSolution, RiccatiFactor


@dataclass
class InitialRows:
    """The initial rows at ``x_0``: values ``e0 (B, m0)`` and Jacobian ``E0 (B, m0, nx)``."""

    e0: Tensor
    E0: Tensor


class InitialState:
    """The free initial state of a solve: which components are free, the user's rows ``h_0(x_0, p)`` and the given
    ``x̄_0 (B, nx)`` that the fixed components keep."""

    def __init__(self, free: Union[bool, Sequence[int]], initial_eq: Optional[Callable], x0: Tensor):
        nx = x0.shape[-1]
        free_mask = torch.zeros(nx, dtype=torch.bool)
        if free is True:
            free_mask[:] = True
        else:
            free_mask[list(free)] = True
        fixed = (~free_mask).nonzero().squeeze(-1).tolist()
        self.x0 = x0
        self.fixed = torch.tensor(fixed, dtype=torch.long, device=x0.device)
        self.selection = torch.eye(nx, dtype=x0.dtype, device=x0.device)[self.fixed]  # (m_fixed, nx)
        self.initial_eq = initial_eq

    def evaluate(self, x: Tensor, params, jacobian: bool = False) -> InitialRows:
        """The rows at ``x (B, *E, nx)``: ``e0 (B, *E, m0)`` and, with ``jacobian`` (then ``x (B, nx)``),
        ``E0 (B, m0, nx)``."""
        lead = x.shape[:-1]
        shift = self.x0.reshape(self.x0.shape[0], *([1] * (x.dim() - 2)), -1)
        values = [(x - shift)[..., self.fixed]]
        jacobians = [self.selection.expand(*lead, *self.selection.shape)]
        if self.initial_eq is not None:
            if jacobian:
                h0, H0 = terminal_jacobian(self.initial_eq, x, params)
                jacobians.append(H0)
            else:
                h0 = map_state(self.initial_eq, x, params)
            values.append(h0)
        return InitialRows(e0=torch.cat(values, -1), E0=torch.cat(jacobians, -2) if jacobian else None)

    def curvature(self, x: Tensor, mu0: Tensor, params) -> Optional[Tensor]:
        """``∇²(μ_0ᵀ h_0)(x) (B, nx, nx)``, the initial rows' part of the Lagrangian Hessian at ``x_0`` (``None``:
        no user rows; the fixed components' rows are linear)."""
        if self.initial_eq is None:
            return None
        nx, fixed, fn = x.shape[-1], self.fixed.numel(), self.initial_eq

        def hessian(xm, p):
            weights = xm[nx + fixed:]
            return jacrev(jacrev(lambda x_: (weights * fn(x_, p)).sum()))(xm[:nx])

        return map_state(hessian, torch.cat([x, mu0], -1), params)


@dataclass
class InitialStep:
    """The stage-0 solve: ``dx0 (B, nx)``, ``eta0 (B, nx)`` (``η_0``), ``mu0 (B, m0)`` and ``ok (B,)``, the reduced
    Hessian positive definite."""

    dx0: Tensor
    eta0: Tensor
    mu0: Tensor
    ok: Tensor


def initial_step(factor: RiccatiFactor, first: LQRSolution, rows: InitialRows) -> InitialStep:
    """Solve the stage-0 system of the module docstring, from the factorisation and one solve (any ``δx_0``: the
    backward sweep that gives ``p_0`` and ``g_0`` does not read it)."""
    P0, p0 = factor.P[:, 0], first.p[:, 0]
    B, nx = p0.shape
    if factor.stage is not None:
        G0, on, g0 = factor.stage[0].G, factor.stage[0].gmask, first.g0
    else:
        G0, on, g0 = P0.new_zeros(B, nx, nx), p0.new_zeros(B, nx), p0.new_zeros(B, nx)
    E0, e0 = rows.E0, rows.e0
    m0 = e0.shape[-1]
    n = 2 * nx + m0
    K = P0.new_zeros(B, n, n)
    K[:, :nx, :nx] = 0.5 * (P0 + P0.transpose(-1, -2))
    K[:, nx:2 * nx, :nx] = G0
    K[:, :nx, nx:2 * nx] = G0.transpose(-1, -2)
    K[:, nx:2 * nx, nx:2 * nx] = torch.diag_embed(on - 1.0)
    K[:, 2 * nx:, :nx] = E0
    K[:, :nx, 2 * nx:] = E0.transpose(-1, -2)
    rhs = -torch.cat([p0, g0 * on, e0], -1)
    finite = torch.isfinite(K).flatten(1).all(-1) & torch.isfinite(rhs).all(-1)
    K = torch.where(finite.reshape(B, 1, 1), K, torch.eye(n, dtype=K.dtype, device=K.device))
    rhs = torch.where(finite.unsqueeze(-1), rhs, torch.zeros_like(rhs))
    values, vectors = torch.linalg.eigh(K)
    scale = values.abs().amax(-1, keepdim=True).clamp_min(torch.finfo(K.dtype).tiny)
    kept = values.abs() > n * torch.finfo(K.dtype).eps * scale
    inverse = torch.where(kept, 1.0 / torch.where(kept, values, torch.ones_like(values)), torch.zeros_like(values))
    solution = vectors @ (inverse * (vectors.transpose(-1, -2) @ rhs.unsqueeze(-1)).squeeze(-1)).unsqueeze(-1)
    solution = solution.squeeze(-1)
    positive = ((values > 0) & kept).sum(-1)
    return InitialStep(dx0=solution[:, :nx], eta0=solution[:, nx:2 * nx] * on, mu0=solution[:, 2 * nx:],
                       ok=finite & (positive == nx))
