r"""The batched Riccati (LQR) core that every solver and the implicit backward pass share.

It solves, for a batch of B instances at once, the time-varying LQR problem

.. math::

    \min_{\delta x, \delta u}\; \sum_{k=0}^{N-1} \tfrac12 \delta x_k^T Q_k \delta x_k
        + \delta u_k^T S_k \delta x_k + \tfrac12 \delta u_k^T R_k \delta u_k
        + q_k^T \delta x_k + r_k^T \delta u_k
        \;+\; \tfrac12 \delta x_N^T Q_N \delta x_N + q_N^T \delta x_N

    \text{s.t.}\quad \delta x_{k+1} = A_k \delta x_k + B_k \delta u_k + c_k,
    \quad \delta x_0 = \bar x_0,
    \quad C_k \delta x_k + D_k \delta u_k + e_k = 0,
    \quad C_N \delta x_N + e_N = 0,

with cross terms ``S``, affine dynamics terms ``c`` (multiple-shooting defects) and stagewise
equality constraints whose rows may be switched off per instance by a mask.

Equality constraints are handled by the generalised Riccati recursion with constraint
back-propagation (Horizon eILQR, Laurenzi et al. §II-B/C; FATROP, Vanroye et al. 2023,
its reference [30]); rows declared simple bounds on the controls hold them without it.
The value function ``V_k(δx) = ½ δxᵀ P_k δx + p_kᵀ δx`` follows by substitution
(ALTRO eqs. 14-15), and the costate obeys ``λ_k = P_k δx_k + p_k + G_kᵀ η_k`` (Horizon eq. 5a).

The recursion is split into :func:`factorize` (matrices only) and
:meth:`RiccatiFactor.solve` (right-hand sides only), so a new right-hand side — the adjoint
system of implicit differentiation, a second-order correction — costs one cheap sweep.
Multipliers (costates ``λ``, constraint multipliers ``ν``) are recovered by a forward sweep.

The files, in the order they build on each other (``torchtraj.riccati.<file>``):

- ``lqr``: the problem's data (:class:`LQR`, :class:`LQRVectors`) and one solution (:class:`LQRSolution`);
- ``linalg``: the small batched Cholesky factorisations and solves, padding, time-major stacking;
- ``sanitize``: instances with non-finite entries swapped for a benign problem (:func:`all_finite`);
- ``propagation``: the constraint back-propagation (SVD split, compression of the rows handed on, multipliers);
- ``bounds``: rows declared simple bounds, which hold controls without the back-propagation;
- ``factor``: :class:`RiccatiFactor` and its solve, forward and multiplier sweeps;
- ``factorization``: :func:`factorize`, the backward sweep over the matrices, and :func:`solve_lqr`;
- ``square_root``: ALTRO's square-root backward pass, giving the same :class:`RiccatiFactor`;
- ``parallel_scan``, ``parallel``: the parallel-in-time sweep (``factorize(..., sweep="parallel")``), associative
  scans over the stages, O(log N) deep, for problems without back-propagated rows;
- ``range_space``: terminal rows by their Schur complement on either unconstrained sweep
  (``factorize(..., terminal_rows="range-space")``), the interior point's default.
"""

from .factor import RiccatiFactor
from .factorization import factorize, solve_lqr
from .lqr import LQR, LQRSolution, LQRVectors
from .parallel import sweep_for_batch
from .propagation import default_rank_tolerance
from .sanitize import all_finite

__all__ = [
    "LQR",
    "LQRSolution",
    "LQRVectors",
    "RiccatiFactor",
    "all_finite",
    "default_rank_tolerance",
    "factorize",
    "solve_lqr",
    "sweep_for_batch",
]
