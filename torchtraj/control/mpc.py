r"""Model predictive control: a batch of trajectory problems re-solved from the measured states at every step.

At control step t, for every instance i of a batch with measured state :math:`\hat x^i_t`, the controller solves
the problem template (:class:`~torchtraj.Problem`, horizon N) from that state,

.. math::

    \min_{x, u}\ \sum_{k<N} \ell(x_k, u_k, p^i) + \ell_N(x_N, p^i)
    \quad \text{s.t.}\quad x_{k+1} = f(x_k, u_k, p^i),\ x_0 = \hat x^i_t,\ \text{the template's constraints},

with a fixed budget of solver iterations, and applies the first control :math:`u^i_0`, clamped to the control
bounds. The iterations are not run to convergence: the warm start carries the work of earlier steps forward
("real-time iteration"). The previous solution is shifted by one step,

.. math::

    U^{\text{warm}} = (u_1, \dots, u_{N-1}, u_{N-1}), \qquad
    \lambda^{\text{warm}}_k = \lambda_{k+1}\ (k < N-1), \quad \lambda^{\text{warm}}_{N-1} = \lambda_{N-1},

(the controls and the duals the method carries: its multipliers, and the interior point's costates as well;
terminal multipliers and the interior point's barrier parameter are kept), and the solver starts from
the rollout of :math:`U^{\text{warm}}` from the measured state; a method that
:attr:`~torchtraj.solvers.base.Solver.starts_from_shifted_states` (multiple shooting: the interior point) starts
from the shifted states :math:`X^{\text{warm}} = (\hat x_t, x_2, \dots, x_N, x_N)` instead, and no rollout is made.

The controller never names a method: it asks the method's :class:`~torchtraj.solvers.base.Solver` object, from the
registry, for

- the options of a step (:meth:`~torchtraj.solvers.base.Solver.step_options`): the given options, or the method's
  defaults for a control step, with the iteration budget and, with ``compile``, compiled kernels;
- the arguments of a warm-started solve (:meth:`~torchtraj.solvers.base.Solver.warm_start`), from the shifted
  controls and carried multipliers;
- the duals to carry to the next step (:meth:`~torchtraj.solvers.base.Solver.carried_duals`), none for a
  method that takes no warm-started duals (ALTRO carries its multipliers; the interior point its multipliers,
  costates and last barrier parameter, :mod:`torchtraj.solvers.ipm.warm_start`).

The shifted states are passed only to such a method: ALTRO's ``X0`` would switch to its infeasible start, a
different problem with slack controls and costs, and its rollout of the shifted controls reproduces the shifted
states up to the last knot where the model is the plant's. A cold instance (the first step, after a reset or a
failure) starts from the method's own start: in a batch whose other instances are warm, the states the method
gives for a solve without ``X0`` (:meth:`~torchtraj.solvers.base.Solver.start_states`), so that one instance's
start never depends on another's.

The penalties restart at ``penalty_initial`` each step: carried over, ALTRO's schedule would multiply them by
``penalty_scaling`` at every step until they reach ``penalty_max`` and the problem becomes ill-conditioned.

With ``iterations`` set, each step runs at most that many iterations; ALTRO runs one inner AL-iLQR solve of at
most ``iterations`` iLQR iterations (``iterations_inner = iterations``, ``iterations_outer = 1``) and carries
multipliers improved by one update (eq. 17, with ``μ = penalty_initial``, :mod:`torchtraj.solvers.altro`). The
default method, the interior point (``tt.solve``'s for a constrained problem), spends its budget adaptively: an
instance whose plan is feasible after one iteration (``IPOptions.stop_feasible_after`` in its step options) ends
there, and one whose plan is not takes more, up to ``iterations``. An instance that spends its budget reports
``Status.MAX_ITERATIONS``; its controls are still the best iterate and are applied.

Warm starts are per instance: :meth:`MPC.reset` with a ``(B,)`` mask drops those of the instances whose episode
restarted (a vector environment's autoreset), by masks and ``torch.where``, with no loop over the batch. An instance
whose solve fails (``NON_FINITE``, ``DIVERGED``, ``INFEASIBLE_START`` or non-finite controls) applies its warm-start
control instead (clamped) and starts cold at the next step; it never changes another instance's answer.
"""

from __future__ import annotations

import time
import warnings
from typing import Callable, Mapping, Optional, Union

import numpy as np
import torch
from torch import Tensor

from .. import solvers
from ..core.batch import Batch
from ..core.constraints import Constraints, map_duals
from ..core.masks import RowPicker, where_rows
from ..core.problem import Problem
from ..core.solution import Solution
from ..core.status import Status
from ..solve import Method, check_problem_and_method, eager_despite_compile, solve

#: ALTRO's control-step options when none are given: its ``step_defaults``, ALTRO without
#: the projection (:data:`torchtraj.solvers.altro.MPC_OPTIONS`). Kept under this name for the callers that build on it.
DEFAULT_ALTRO = solvers.get("altro").step_defaults()


def _shift(t: Tensor) -> Tensor:
    """``(B, N, ...)`` moved one step earlier along N, the last entry repeated."""
    return torch.cat([t[:, 1:], t[:, -1:]], 1)


class MPC(torch.nn.Module):
    """A receding-horizon policy: ``MPC(problem)(observations) -> first controls``; see the module docstring.

    Args:
        problem: the template: dynamics, costs, constraints, horizon and parameters. Its ``x0`` is replaced at each
            call by the measured states; its ``u_init`` is the cold start.
        method: a registered method (:func:`torchtraj.solvers.names`), checked here: an unknown name is a
            ``ValueError`` listing the valid ones; a method that ignores constraints, as ``"ilqr"``, on a
            constrained problem warns once, here, rather than at every control step. Default ``"ipm"``, the
            interior point with its adaptive budget (module docstring; its controllers' acceptance runs and
            timings against ALTRO's: ``docs/benchmarks.md``, "MPC").
        iterations: solver iterations per control step (the method's ``step_options``: ALTRO's
            ``iterations_inner`` with ``iterations_outer = 1``, the others' ``iterations``; the interior point's
            steps end sooner where their plan is feasible). ``None`` uses ``options`` as given.
        options: the method's options; default its control-step options
            (:meth:`~torchtraj.solvers.base.Solver.step_defaults`: :data:`DEFAULT_ALTRO` for ALTRO,
            :meth:`IPM.step_defaults <torchtraj.solvers.ipm.IPM.step_defaults>` for the interior point).
        observation_to_state: maps observations ``(B, n_obs)`` (torch, in the problem's dtype) to states
            ``(B, nx)``; default identity.
        observation_to_params: maps observations to per-instance parameters ``{name: (B, ...)}`` (a car's observed
            obstacles); default none.
        compile: ``torch.compile`` the solver's kernels (sets the options' ``compile``, see
            :mod:`torchtraj.core.compiled`): the first calls for a batch size compile (tens of seconds to minutes),
            and the later steps are faster (``docs/benchmarks.md``, "MPC"). A method without compiled kernels
            (:attr:`~torchtraj.solvers.base.Solver.compiles`: a registered method of one's own) warns here and
            runs eager.

    Call: ``mpc(observations, params=None)`` with observations ``(n_obs,)`` or ``(B, n_obs)``, numpy or torch,
    returns controls ``(nu,)`` or ``(B, nu)`` of the same kind (numpy float64, or a tensor of the observations'
    dtype and device). ``params`` are per-call parameters ``{name: (B, ...) or per-instance shape}`` that
    override the template's; the problem is rebuilt only when they change (a reset's new obstacle layout).

    After a call: :attr:`solution` (the last :class:`~torchtraj.Solution`), :attr:`X` ``(B, N+1, nx)`` and
    :attr:`U` ``(B, N, nu)`` the predicted trajectories, :attr:`status` ``(B,)``, :attr:`solve_seconds`.
    """

    def __init__(self, problem: Problem, method: Union[str, Method, solvers.Solver] = "ipm",
                 iterations: Optional[int] = 3, options=None, observation_to_state: Optional[Callable] = None,
                 observation_to_params: Optional[Callable] = None, compile: bool = False):
        super().__init__()
        solver = check_problem_and_method(problem, method)
        self._ignores_constraints = problem.has_constraints and not solver.handles_constraints
        if self._ignores_constraints:
            warnings.warn(f"MPC: method {solver.name!r} ignores the constraints of problem {problem.name!r}; the "
                          "controls are clamped to the control bounds and the state constraints are not enforced",
                          UserWarning, stacklevel=2)
        if iterations is not None and (int(iterations) != iterations or iterations < 1):
            raise ValueError(f"iterations must be a positive int or None, got {iterations!r}")
        self.problem, self.solver, self.method = problem, solver, solver.name
        self.options = solver.step_options(options, iterations, compile)
        if eager_despite_compile(solver, self.options):  # said once, here: the steps' options ask for no kernels
            warnings.warn(f"MPC: method {solver.name!r} has no compiled kernels: compile=True runs it eager",
                          UserWarning, stacklevel=2)
            self.options = solver.with_kernels(self.options, compile=False)
        self.observation_to_state = observation_to_state
        self.observation_to_params = observation_to_params
        self._template = problem
        bad = (Status.NON_FINITE, Status.DIVERGED, Status.INFEASIBLE_START)
        self._failures = torch.tensor([int(b) for b in bad], device=problem.device)
        self._params: dict = {}
        self.solution: Optional[Solution] = None
        self.solve_seconds = float("nan")
        self._clear(0)

    # ------------------------------------------------------------------ warm start
    def _clear(self, batch: int) -> None:
        p = self.problem
        self._U = p.u_init.expand(batch, p.N, p.nu).clone()
        self._X = None if not self.solver.starts_from_shifted_states else p.x0.new_zeros(batch, p.N + 1, p.nx)
        self._duals: dict = {}
        self._warm = torch.zeros(batch, dtype=torch.bool, device=p.device)

    @property
    def batch_size(self) -> int:
        """Batch size of the current warm start (0 before the first call)."""
        return int(self._warm.shape[0])

    def reset(self, mask=None) -> None:
        """Drop the warm start of every instance, or of those where ``mask (B,)`` (bool, numpy or torch) is true."""
        if mask is None or self.batch_size == 0:  # nothing to drop before the first call
            self._warm = torch.zeros_like(self._warm)
            return
        mask = torch.as_tensor(np.asarray(mask) if not isinstance(mask, Tensor) else mask, device=self._warm.device)
        if mask.dtype != torch.bool or mask.shape != self._warm.shape:
            raise ValueError(f"mask must be a bool array of shape ({self.batch_size},), got {mask.dtype} "
                             f"{tuple(mask.shape)}")
        self._warm = self._warm & ~mask

    def warm_start(self, warm: Optional[int] = None) -> tuple[Tensor, Optional[dict]]:
        """The next solve's initial controls ``(B, N, nu)`` and duals (``tt.solve``'s, as the method carries them):
        shifted where warm; elsewhere the problem's controls and zero duals (which a method reads as its cold
        start: ALTRO's multipliers start at zero, the interior point starts cold where the barrier is 0); no duals
        (``None``) where every instance is cold. ``warm``: the number of warm instances, where the caller has read
        it (else read here); with every instance warm, the carried values are used as they are."""
        warm = int(self._warm.sum()) if warm is None else warm
        cold = self.problem.u_init.expand_as(self._U)
        if warm == 0:
            return cold, None
        if warm == self.batch_size:
            return self._U, self._duals or None
        U0 = where_rows(self._warm, self._U, cold)
        if not self._duals:
            return U0, None
        pick = RowPicker(self._warm)
        return U0, map_duals(self._duals, lambda v: pick(v, torch.zeros_like(v)))

    def start_states(self, x: Tensor, U0: Tensor, warm: Optional[int] = None) -> Optional[Tensor]:
        """The next solve's initial states ``(B, N+1, nx)`` for a method that starts from shifted states: the shifted
        states after the measured ``x`` where warm, the method's own cold start elsewhere; ``None`` where every
        instance is cold or the method takes none. ``warm``: the number of warm instances (else read here)."""
        if self._X is None:
            return None
        warm = int(self._warm.sum()) if warm is None else warm
        if warm == 0:
            return None
        X = torch.cat([x.unsqueeze(1), self._X[:, 1:]], 1)
        if warm == self.batch_size:
            return X
        cold = self.solver.start_states(self.problem, Batch.build(self.problem, x, U0), self.options)
        return where_rows(self._warm, X, cold)

    # ------------------------------------------------------------------ the policy
    def forward(self, observations, params: Optional[Mapping] = None):
        is_numpy = not isinstance(observations, Tensor)
        obs = torch.as_tensor(np.asarray(observations) if is_numpy else observations)
        out_dtype, out_device = (torch.float64, "cpu") if is_numpy else (obs.dtype, obs.device)
        single = obs.dim() == 1
        obs = obs.reshape(1, -1) if single else obs
        if obs.dim() != 2:
            raise ValueError(f"observations must have shape (n_obs,) or (B, n_obs), got {tuple(obs.shape)}")
        obs = obs.to(dtype=self.problem.dtype, device=self.problem.device)
        x = self.observation_to_state(obs) if self.observation_to_state is not None else obs
        if x.shape != (obs.shape[0], self.problem.nx):
            raise ValueError(f"states must have shape (B, {self.problem.nx}), got {tuple(x.shape)}; "
                             "pass observation_to_state for observations that are not the state")
        given = dict(self.observation_to_params(obs)) if self.observation_to_params is not None else {}
        given.update(params or {})
        self._use_params(given)
        if x.shape[0] != self.batch_size:
            self._clear(x.shape[0])
        u = self._step(x)
        u = u.to(dtype=out_dtype, device=out_device)
        u = u[0] if single else u
        return u.numpy() if is_numpy else u

    def _use_params(self, given: dict) -> None:
        """Rebuild the problem from the template only when the per-call parameters change."""
        given = {k: torch.as_tensor(v, dtype=self.problem.dtype, device=self.problem.device) for k, v in given.items()}
        same = given.keys() == self._params.keys() and all(
            v.shape == self._params[k].shape and bool(torch.equal(v, self._params[k])) for k, v in given.items())
        if not same:
            given = {k: v.clone() for k, v in given.items()}  # never an alias of the caller's observations
            self.problem = self._template.with_params(**given) if given else self._template
            self._params = given

    @torch.no_grad()
    def _step(self, x: Tensor) -> Tensor:
        p = self.problem
        warm = int(self._warm.sum())  # the step's one read of the warm count
        U0, duals = self.warm_start(warm)
        X0 = self.start_states(x, U0, warm)
        start = time.perf_counter()
        with warnings.catch_warnings():
            if self._ignores_constraints:  # said once, at construction
                warnings.filterwarnings("ignore", message=".*ignores the constraints")
            sol = solve(p, x, self.solver, options=self.options, **self.solver.warm_start(U0, duals, X0))
        self.solve_seconds = time.perf_counter() - start
        failed = torch.isin(sol.status, self._failures) | ~torch.isfinite(sol.U).flatten(1).all(-1)
        usable = ~failed
        u = where_rows(usable, sol.U[:, 0], U0[:, 0])
        lower = p.u_lower if p.u_lower is not None else torch.full_like(u[0], -torch.inf)
        upper = p.u_upper if p.u_upper is not None else torch.full_like(u[0], torch.inf)
        u = torch.clamp(u, lower, upper)
        self.solution = sol
        self._U = _shift(where_rows(usable, sol.U, U0))
        if self._X is not None:  # a failed instance's states are not used: it starts cold
            self._X = _shift(sol.X)
        carried = {}
        if self.solver.takes_duals:  # else none to carry, and no constraints to make for it
            carried = self.solver.carried_duals(Constraints.of(p), sol, self.options)
        self._duals = map_duals(carried, lambda v: _shift(v) if v.dim() == 3 else v)  # per-knot entries shifted
        self._warm = usable
        return u

    # ------------------------------------------------------------------ diagnostics
    @property
    def X(self) -> Optional[Tensor]:
        """Predicted states ``(B, N+1, nx)`` of the last call."""
        return None if self.solution is None else self.solution.X

    @property
    def U(self) -> Optional[Tensor]:
        """Predicted controls ``(B, N, nu)`` of the last call (before clamping)."""
        return None if self.solution is None else self.solution.U

    @property
    def status(self) -> Optional[Tensor]:
        """Solver status ``(B,)`` of the last call (:class:`~torchtraj.Status` codes)."""
        return None if self.solution is None else self.solution.status

    def extra_repr(self) -> str:
        its = getattr(self.options, "iterations_inner", getattr(self.options, "iterations", None))
        p = self.problem
        return f"problem={p.name!r}, method={self.method!r}, horizon={p.N}, iterations={its}"
