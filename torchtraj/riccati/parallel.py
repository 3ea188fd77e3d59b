r"""The parallel-in-time Riccati sweep: the LQR's backward and forward passes as associative scans, O(log N) deep.

Following Särkkä & García-Fernández, "Temporal parallelization of dynamic programming and linear quadratic
control" (IEEE TAC 2023, arXiv 2104.03186; its section on parallel linear quadratic tracking), the cost of going
from ``x`` at stage ``i`` to ``y`` at stage ``j`` optimally, the conditional value function, is kept in the form

.. math::  V_{i\to j}(x, y) = \tfrac12 x^T J x - \eta^T x
           + \max_\lambda \big[\lambda^T (y - A x - b) - \tfrac12 \lambda^T C \lambda\big] + \text{const},

an element ``(A, b, C, η, J)``. One stage with ``x_{k+1} = A_k x + B_k u + c_k`` and the stage cost of the package
docstring is such an element once its control is minimised out for given end points: with ``u = w − R^{-1}(S x +
r)``,

.. math::  A_e = A - B R^{-1} S,\quad b_e = c - B R^{-1} r,\quad C_e = B R^{-1} B^T,\quad
           J_e = Q - S^T R^{-1} S,\quad \eta_e = S^T R^{-1} r - q,

and the terminal cost is the element ``(0, 0, 0, −q_N, Q_N)``. Minimising over the middle point joins two
elements, earlier ``1`` and later ``2`` (the paper's associative operator of the LQ elements):

.. math::  A_{12} &= A_2 (I + C_1 J_2)^{-1} A_1, &\quad C_{12} &= A_2 (I + C_1 J_2)^{-1} C_1 A_2^T + C_2,\\
           J_{12} &= A_1^T (I + J_2 C_1)^{-1} J_2 A_1 + J_1, &\quad
           \eta_{12} &= A_1^T (I + J_2 C_1)^{-1} (\eta_2 - J_2 b_1) + \eta_1,

an associative operation: the reverse scan (:mod:`~torchtraj.riccati.parallel_scan`) of the stage elements and the
terminal one gives, at every ``k``, the value function's Hessian ``P_k = J_{k→N}`` in ``⌈log₂(N+1)⌉`` levels. The
gains then follow for all stages in one batched call, ``K_k = −Q_{uu}^{-1} Q_{ux}`` from ``P_{k+1}``.

A right-hand side's value-function gradients obey the affine recursion (the exact minimiser makes
``Q_uu k_k + Q_u = 0``) ``p_k = (A_k + B_k K_k)^T (P_{k+1} c_k + p_{k+1}) + q_k + K_k^T r_k``, ``p_N = q_N``, and
the step the closed-loop one ``δx_{k+1} = (A_k + B_k K_k) δx_k + B_k k_k + c_k``: both are scans of affine maps
(the paper's parallel forward pass). The vector part ``b, η`` of the elements therefore never needs scanning.

Held bounds (:mod:`~torchtraj.riccati.bounds`): with ``F`` the free controls and ``h`` the held ones' values,
``u = F v + h`` turns the stage into one with ``R̃ = F R F + I − F``, ``S̃ = F S``, ``B̃ = B F``, ``r̃ = F (r + R h)``,
``q̃ = q + S^T h``, ``c̃ = c + B h``: the held controls are eliminated stage by stage before the elements are built,
and the gains are those of the sequential sweep, ``K = −(F Q_uu F + I − F)^{-1} F Q_ux``.

Differences from the sequential sweep (:func:`~torchtraj.riccati.factorize`):

- the elements need each stage's (reduced) control Hessian ``R̃`` positive definite, where the sequential sweep
  needs only ``Q_uu``: :func:`factorize_parallel` flags such an instance not ``ok``, and
  :func:`~torchtraj.riccati.factorize` (without ``ρ``) factorises it again by the sequential sweep
  (:meth:`ParallelRiccatiFactor.with_rows`), so that its verdict is the sequential sweep's; so too an instance whose
  ``Q_uu`` failed the inertia test, unless its value functions meet the sequential sweep's recursion
  (:meth:`ParallelRiccatiFactor.settled`): an interior point's inertia correction tries shifts that leave the
  system indefinite, and factorising each again only repeated the verdict;
- the scan is not backward stable on ill-conditioned stages (an interior point's barrier near convergence): with
  some stages' ``Q`` and ``R`` scaled by 1e10 its value function is 1e-5 from the sequential sweep's, and its steps
  meet the stationarity rows to a relative residual of 1 where the sequential sweep's meet them to 2e-6;
- ``ρ`` (``regularization``) is a proximal term ``½ ρ |δu|²`` of the problem, in the gains *and* the value
  function: the sequential sweep's value function along the regularised gains
  (``P = Q_xx + K^T Q_ux − ρ K^T K``) is not the value function of any LQR and has no associative form. At
  ``ρ = 0`` both give the same step to round-off.
- constraint rows that take the back-propagation (``LQR.propagated``) have no parallel form here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import partial
from typing import Optional

import torch
from torch import Tensor

from ..core.compiled import addmatmul as _addmm
from ..core.compiled import matmul as _mm
from .bounds import _bound_multipliers, _held_controls, _held_values
from .factor import RiccatiFactor
from .linalg import _batch_first, _cholesky, _cholesky_solve, _factored_solve, _mT, _solve, _sym
from .lqr import LQR, LQRSolution, LQRVectors
from .parallel_scan import affine_scan, associative_scan
from .sanitize import _sanitize_stacked, all_finite

SWEEPS = ("sequential", "parallel", "auto")


#: ``"auto"`` on CPU takes the parallel sweep while ``B · ⌈log₂(N+1)⌉ · (nx+nu)² ≤`` this (:func:`choose_sweep`).
AUTO_CPU_WORK = 5500
#: ... and from this horizon on (every device).
AUTO_MIN_HORIZON = 8


def choose_sweep(lqr: LQR, sweep: str) -> str:
    """``"sequential"`` or ``"parallel"``: the sweep that :func:`~torchtraj.riccati.factorize` runs for ``sweep``.

    ``"auto"`` takes the parallel sweep where it applies (no back-propagated rows) and where
    :func:`sweep_for_batch` says it pays for ``lqr``'s sizes."""
    if sweep not in SWEEPS:
        raise ValueError(f"sweep must be one of {', '.join(SWEEPS)}, not {sweep!r}")
    if sweep == "sequential":
        return sweep
    if lqr.propagated:
        if sweep == "parallel":
            raise ValueError("the parallel Riccati sweep takes no back-propagated constraint rows (LQR.C, D, CN "
                             "without LQR.bounds): use sweep='sequential' or 'auto'")
        return "sequential"
    if sweep == "parallel":
        return sweep
    B, N, nx, nu = lqr.B.shape
    return sweep_for_batch(B, N, nx, nu, lqr.B.device)


def sweep_for_batch(B: int, N: int, nx: int, nu: int, device: torch.device) -> str:
    """The sweep that ``"auto"`` takes, where the parallel one applies, for a batch of ``B`` problems of horizon ``N``
    with ``nx`` states and ``nu`` controls on ``device``: the parallel sweep from ``N ≥ 8``, on CPU while
    ``B · ⌈log₂(N+1)⌉ · (nx+nu)² ≤ 5500``. The parallel sweep saves the sequential one's per-stage calls but does
    about ``⌈log₂(N+1)⌉`` times its arithmetic, in batched solves of ``nx × nx`` systems; factorise and solve were
    timed on one CPU core for ``nx, nu = 4, 2`` and ``2, 1``, ``B`` from 1 to 256 and ``N`` from 8 to 400, and the
    bound separates the two within the timings' noise (the crossover ``B`` at a given ``N`` falls like
    ``1/(nx+nu)²``). On other devices, where every call is a kernel launch, the rule is the horizon alone: a default
    reasoned from the calls, not a measurement.

    A solver that compacts its batch, or factorises a few instances' rows apart, decides once for the whole batch
    (as the interior point does): deciding per factorisation would give an instance other round-off as the
    instances beside it finish."""
    if N < AUTO_MIN_HORIZON:
        return "sequential"
    if torch.device(device).type != "cpu":
        return "parallel"
    work = B * N.bit_length() * (nx + nu) ** 2  # N.bit_length() = ⌈log₂(N+1)⌉, the levels of the scan
    return "parallel" if work <= AUTO_CPU_WORK else "sequential"


def _time_major(x: Tensor) -> Tensor:
    """``x (B, N, n)`` as a time-major column stack ``(N·B, n, 1)``."""
    return x.transpose(0, 1).reshape(-1, x.shape[-1], 1)


@dataclass
class ParallelRiccatiFactor(RiccatiFactor):
    """A :class:`RiccatiFactor` from :func:`factorize_parallel`; its :meth:`solve` runs the two affine scans.

    ``Quu``, ``Qux`` are the unregularised Q-function blocks and ``chol`` the Cholesky factor of the reduced,
    regularised ``F (Q_uu + ρI) F + I − F``, as the sequential sweep's; ``time_major`` holds the same tensors (and
    ``W = [A B]``, ``H = [[Q, Sᵀ], [S, R]]``, the closed loop ``Φ = A + B K``) stored time-major and flattened,
    ``(N·B, …)``, the layout of the scans."""

    time_major: Optional[dict] = None
    #: ``(B,)``: every stage's ``R̃`` was positive definite, so the scan's elements are those of the instance's stages
    built: Optional[Tensor] = None

    def solve(self, rhs: LQRVectors, multipliers: bool = False, forward: bool = True,
              initial_multiplier: Optional[Tensor] = None) -> LQRSolution:
        """Solve the LQR problem for ``rhs``: the gradients ``p`` by a reverse affine scan, the feedforward of all
        stages at once, the step by a forward affine scan (module docstring; the step is computed whatever
        ``forward``, its scan being O(log N) deep; without back-propagated rows no rows are left at the initial
        state, and ``initial_multiplier`` has nothing to apply to)."""
        tm, lqr = self.time_major, self.lqr
        B, nx = lqr.B.shape[0], lqr.A.shape[-1]
        K, Phi, Quu, W = tm["K"], tm["Phi"], tm["Quu"], tm["W"]
        Bu = W[..., nx:]
        P_next = tm["P"][B:]
        c, q, r = _time_major(rhs.c), _time_major(rhs.q), _time_major(rhs.r)
        qN = rhs.qN.unsqueeze(-1)
        Pc = _mm(P_next, c)
        held = _held_values(self.fixed, lqr, rhs)
        if held is not None:  # the held controls' values moved into the stage's vectors
            H, held, free = tm["H"], _time_major(held), tm["free"]
            Pc_held = _addmm(Pc, _mm(P_next, Bu), held)
            q_held = _addmm(q, _mT(H[..., nx:, :nx]), held)
            r_held = _addmm(r, H[..., nx:, nx:], held)
        else:
            Pc_held, q_held, r_held = Pc, q, r
        g = _addmm(_addmm(q_held, _mT(K), r_held), _mT(Phi), Pc_held)
        p = torch.cat([affine_scan(_mT(Phi), g, qN, reverse=True), qN])
        Qu = _addmm(r, _mT(Bu), Pc + p[B:])
        if held is not None:
            k = held - _cholesky_solve(_addmm(Qu, Quu, held) * free, tm["chol"])
        else:
            k = -_cholesky_solve(Qu, tm["chol"])
        Quuk = _mm(Quu, k)
        dV1 = (k * Qu).unflatten(0, (-1, B)).sum((0, 2, 3))
        dV2 = 0.5 * (k * Quuk).unflatten(0, (-1, B)).sum((0, 2, 3))
        x0 = rhs.x0.unsqueeze(-1)
        dx = torch.cat([x0, affine_scan(Phi, _addmm(c, Bu, k), x0)])
        du = _addmm(k, K, dx[:-B])
        out = LQRSolution(dx=_batch_first(dx, B), du=_batch_first(du, B), k=_batch_first(k, B),
                          p=_batch_first(p, B), dV1=dV1, dV2=dV2)
        if multipliers:
            self._parallel_multipliers(rhs, out, dx, du, p, Qu)
        return out

    def with_rows(self, index: Tensor, other: RiccatiFactor) -> "ParallelRiccatiFactor":
        """This factor with the instances ``index (b,)`` replaced by ``other``, a sequential factor of the same
        problem's rows ``index`` (``LQR.rows``; :func:`~torchtraj.riccati.factorize`'s fallback). ``other`` has
        no back-propagated rows, so its ``K``, ``P``, ``Q_uu``, ``Q_ux`` and ``chol`` are the blocks this factor
        holds, of the same meaning (class docstring)."""
        B, nx = self.lqr.B.shape[0], self.lqr.A.shape[-1]
        tm = dict(self.time_major)
        for name in ("K", "P", "Quu", "chol"):  # time-major (T·B, …) ← batch-first (b, T, …)
            tm[name] = tm[name].unflatten(0, (-1, B)).index_copy(1, index, getattr(other, name).transpose(0, 1)
                                                                  ).flatten(0, 1)
        W = tm["W"]
        tm["Phi"] = _addmm(W[..., :nx], W[..., nx:], tm["K"])
        return dataclasses.replace(
            self, K=_batch_first(tm["K"], B), P=_batch_first(tm["P"], B), Quu=_batch_first(tm["Quu"], B),
            Qux=self.Qux.index_copy(0, index, other.Qux), chol=_batch_first(tm["chol"], B),
            ok=self.ok.index_copy(0, index, other.ok), time_major=tm, built=self.built.index_fill(0, index, True))

    def settled(self, index: Tensor) -> Tensor:
        """``(b,)``: whether the instances ``index``, which this factor flags not ``ok``, fail the sequential sweep's
        inertia test as well, so that factorising them again (:func:`~torchtraj.riccati.factorize`'s fallback) would
        only repeat the verdict.

        The test of a stage's ``Q_uu`` is the sequential sweep's; what can differ is the ``P_{k+1}`` it is built
        from, as the scan is not backward stable on ill-conditioned systems (module docstring). So an instance is
        settled where the scan built its elements (``built``) and its value functions meet the sequential sweep's
        one-stage recursion ``P_k = sym(E_kᵀ Ĥ_k E_k)``, ``Ĥ_k = H_k + W_kᵀ P_{k+1} W_k``, ``E_k = [I; K_k]`` with
        the exact gain ``K_k = −Q_uu⁻¹ Q_ux`` of the (indefinite) stage, to ``1e2 √ε`` of the terms'
        ``|Ĥ_k| (1 + |K_k|)²`` at every stage: its ``P`` is then one the sequential sweep's rounding could have
        made, and so is the ``Q_uu`` that failed. Where the scan went wrong (an ill-conditioned system), its ``P``
        misses the recursion by orders of magnitude and the instance is factorised again (``docs/benchmarks.md``
        has the interior point's counts on the problem set)."""
        tm, B = self.time_major, self.ok.shape[0]
        b, nx = index.numel(), self.lqr.A.shape[-1]

        def rows(a: Tensor) -> Tensor:  # the instances index of a time-major stack (T·B, …), as (T·b, …)
            return a.unflatten(0, (-1, B)).index_select(1, index).flatten(0, 1)

        W, H, P = rows(tm["W"]), rows(tm["H"]), rows(tm["P"])
        Hq = _addmm(H, _mT(W), _mm(P[b:], W))
        Hu, Qux = _sym(Hq[..., nx:, nx:]), Hq[..., nx:, :nx]
        if tm["free"] is not None:
            free = rows(tm["free"])
            Hu, Qux = _free_block(Hu, free), Qux * free
        K = -(Qux / Hu if Hu.shape[-1] == 1 else torch.linalg.solve_ex(Hu, Qux)[0])
        E = torch.cat([torch.eye(nx, dtype=K.dtype, device=K.device).expand(K.shape[0], nx, nx), K], -2)
        scale = Hq.abs().amax((-2, -1)) * (1.0 + K.abs().amax((-2, -1))) ** 2
        residual = ((P[:-b] - _sym(_mm(_mT(E), _mm(Hq, E)))).abs().amax((-2, -1)) / scale).unflatten(0, (-1, b))
        tolerance = 1e2 * torch.finfo(K.dtype).eps ** 0.5
        return self.built.index_select(0, index) & (residual <= tolerance).all(0)  # NaN: not settled

    def _parallel_multipliers(self, rhs: LQRVectors, out: LQRSolution, dx: Tensor, du: Tensor, p: Tensor,
                              Qu: Tensor) -> None:
        """The held rows' ``ν`` (all stages at once) and the costates: ``λ_k = P_k δx_k + p_k`` where the gains
        are exact, else the reverse scan of ``λ_k = A_k^T λ_{k+1} + Q_k δx_k + S_k^T δu_k + q_k``."""
        tm, lqr = self.time_major, self.lqr
        B, nx = lqr.B.shape[0], lqr.A.shape[-1]
        if self.fixed is not None:
            out.nu = _bound_multipliers(lqr, self.fixed, self.Quu, self.Qux, out.dx, out.du, _batch_first(Qu, B))
        if self.exact:
            out.costate = _batch_first(_addmm(p, tm["P"], dx), B)
            return
        W, H = tm["W"], tm["H"]
        last = _addmm(rhs.qN.unsqueeze(-1), lqr.QN, dx[-B:])
        g = _addmm(_addmm(_time_major(rhs.q), H[..., :nx, :nx], dx[:-B]), H[..., :nx, nx:], du)
        lam = torch.cat([affine_scan(_mT(W[..., :nx]), g, last, reverse=True), last])
        out.costate = _batch_first(lam, B)


def _free_block(M: Tensor, free: Tensor) -> Tensor:
    """The control Hessian ``M (…, nu, nu)`` with the held controls (``free (…, nu, 1)`` 0) out of the free ones'
    system: ``F M F + I − F`` (the held controls' rows and columns the identity's)."""
    return M * free * _mT(free) + torch.diag_embed((1.0 - free).squeeze(-1))


def _stage_elements(W: Tensor, H: Tensor, rho: Optional[Tensor], held: Optional[Tensor]) -> tuple:
    """The stages' elements ``[A_e, C_e, J_e] (N·B, 3, nx, nx)`` with the held controls eliminated, from the
    time-major blocks ``W (N·B, nx, nx+nu)``, ``H (N·B, nx+nu, nx+nu)``, and the ``info (N·B,)`` of the Cholesky
    factorisation of the reduced ``R̃`` (0 where positive definite)."""
    nx = W.shape[-2]
    R, S, Bu = H[..., nx:, nx:], H[..., nx:, :nx], W[..., nx:]
    if rho is not None:
        R = R + rho
    if held is not None:
        free = 1.0 - held
        R = _free_block(R, free)
        S, Bu = S * free, Bu * _mT(free)
    L, info = _cholesky(R)
    Y = _cholesky_solve(torch.cat([S, _mT(Bu)], -1), L)  # R̃⁻¹ [S̃, B̃ᵀ]
    YS = Y[..., :nx]
    A = _addmm(W[..., :nx], Bu, YS, alpha=-1.0)
    C = _mm(Bu, Y[..., nx:])
    J = _addmm(H[..., :nx, :nx], _mT(S), YS, alpha=-1.0)
    return torch.stack([A, C, J], 1), info


def _join(eye: Tensor, earlier: tuple, later: tuple) -> tuple:
    """``earlier ⊗ later`` of elements ``[A, C, J]`` (module docstring), for all pairs of a level."""
    A1, C1, J1 = earlier[0].unbind(1)
    A2, C2, J2 = later[0].unbind(1)
    nx = A1.shape[-1]
    # (I + C1 J2)⁻¹ [A1, C1] in one solve; (I + J2 C1)⁻¹ = (I + C1 J2)⁻ᵀ gives J's factor from the same one
    T = _solve(_addmm(eye, C1, J2), torch.cat([A1, C1], -1))
    TA = T[..., :nx]
    A12 = _mm(A2, TA)
    C12 = _addmm(C2, _mm(A2, T[..., nx:]), _mT(A2))
    J12 = _addmm(J1, _mT(TA), _mm(J2, A1))
    return (torch.stack([A12, C12, J12], 1),)


def factorize_parallel(lqr: LQR, regularization: Optional[Tensor] = None,
                       shift: Optional[Tensor] = None) -> ParallelRiccatiFactor:
    """The parallel-in-time factorisation of ``lqr`` (module docstring); arguments as
    :func:`~torchtraj.riccati.factorize`, whose ``sweep="parallel"`` calls it. ``regularization ρ (B,)`` is a
    proximal term on the controls here (module docstring)."""
    if lqr.propagated:
        raise ValueError("the parallel Riccati sweep takes no back-propagated constraint rows")
    lqr, finite, W, H = _sanitize_stacked(lqr, shift)
    B, N, nx, nu = lqr.B.shape
    W, H = W.flatten(0, 1), H.flatten(0, 1)  # time-major (N·B, …): the stacked blocks are stored so
    dtype, device = W.dtype, W.device
    held = free = rho = None
    if lqr.bounds is not None:
        held = _held_controls(lqr, dtype)
        held_tm = _time_major(held)
        free = 1.0 - held_tm
    if regularization is not None:
        rho = regularization.repeat(N).reshape(-1, 1, 1) * torch.eye(nu, dtype=dtype, device=device)
    elements, info_R = _stage_elements(W, H, rho, held_tm if held is not None else None)
    terminal = torch.cat([lqr.QN.new_zeros(B, 2, nx, nx), lqr.QN.unsqueeze(1)], 1)
    eye = torch.eye(nx, dtype=dtype, device=device)
    (scanned,) = associative_scan((torch.cat([elements, terminal]),), partial(_join, eye), B, reverse=True)
    P = _sym(scanned[:, 2])
    # every stage's Q-function from P_{k+1} in one batched congruence, the sequential sweep's H + Wᵀ P W
    Hq = _addmm(H, _mT(W), _mm(P[B:], W))
    Quu, Qux = _sym(Hq[..., nx:, nx:]), Hq[..., nx:, :nx]
    Hu = Quu if rho is None else Quu + rho
    if held is not None:  # the held controls out of the free ones' system (bounds._held_gain)
        Hu = _free_block(Hu, free)
        Qux_free = Qux * free
    else:
        Qux_free = Qux
    L, info = _cholesky(Hu)
    K = -_factored_solve(Hu, L, info, Qux_free)
    built = (info_R == 0).reshape(N, B).all(0)
    ok = finite & built & (info == 0).reshape(N, B).all(0) & all_finite([P.reshape(N + 1, B, -1).transpose(0, 1)])
    tm = {"K": K, "P": P, "Quu": Quu, "chol": L, "W": W, "H": H, "free": free,
          "Phi": _addmm(W[..., :nx], W[..., nx:], K)}
    return ParallelRiccatiFactor(
        lqr=lqr, K=_batch_first(K, B), P=_batch_first(P, B), ok=ok, Quu=_batch_first(Quu, B),
        Qux=_batch_first(Qux, B), chol=_batch_first(L, B), free=None, stage=None, terminal=None,
        exact=regularization is None, fixed=held, time_major=tm, built=built,
    )
