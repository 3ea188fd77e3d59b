r"""What a solver is to the rest of the library: a :class:`Solver` object that declares its abilities and solves.

Every method solves the same problem, for each instance i of a batch,

.. math::

    \min_{X, U}\ \sum_{k<N} \ell(x_k, u_k, p^i) + \ell_N(x_N, p^i) \quad\text{s.t.}\quad
    x_{k+1} = f(x_k, u_k, p^i),\ x_0 = x_0^i,\ g(x_k, u_k, p^i) \le 0,\ h(x_k, u_k, p^i) = 0, \dots

(a method that does not handle constraints drops the last ones and reports their violation). ``tt.solve``,
:class:`~torchtraj.MPC` and the benchmarks never branch on a method's name: they read its declarations

- ``handles_constraints``: whether the solution is meant to satisfy the constraints. Its KKT conditions are those
  of the constrained problem, else of the unconstrained one (the implicit layer's ``constrained`` flag);
- ``takes_state_guess``: whether ``X0 (B, N+1, nx)`` is accepted (a multiple-shooting start, or ALTRO's
  infeasible start);
- ``takes_duals``: whether a warm start of the multipliers (``tt.solve``'s ``duals``) is accepted, and
  ``dual_entries`` which of its entries (:data:`~torchtraj.core.constraints.DUAL_ENTRIES`);
- ``starts_from_shifted_states``: whether a control step starts from the previous step's states, shifted by one
  knot, as well as its controls (a multiple-shooting start: the shift replaces the rollout of the shifted controls;
  ALTRO's ``X0`` would be its infeasible start, another problem);
- ``kkt_point``: whether a converged solution is a KKT point the implicit layer
  (:mod:`torchtraj.differentiation.implicit`) can refine and differentiate;
- :meth:`Solver.kkt_problem`: the problem whose KKT point that is, where it is not the one declared above
  (eILQR's inequalities are soft barriers on the cost: its solution is a KKT point of the barrier-augmented,
  equality-constrained problem);

and call its methods: :meth:`Solver.solve` on a checked :class:`~torchtraj.core.batch.Batch`, and the hooks of a
control step (:meth:`Solver.step_options`, :meth:`Solver.warm_start`, :meth:`Solver.carried_duals`). The
registry of :mod:`torchtraj.solvers` holds one object per method.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import ClassVar, Optional

from torch import Tensor

from ..core.batch import Batch
from ..core.batching import rollout
from ..core.constraints import Constraints
from ..core.options import validate
from ..core.problem import Problem
from ..core.solution import Solution


class Solver(abc.ABC):
    """A trajectory-optimisation method: its declarations (module docstring) and its hooks.

    A subclass sets the class attributes and implements :meth:`solve`. The defaults of the control-step hooks
    suit a method whose options dataclass has ``iterations`` and ``compile`` fields and which carries no duals.
    """

    #: The method's name (``tt.solve(..., method=name)``, ``Solution.method``).
    name: ClassVar[str]
    #: The options dataclass; ``options_class()`` are the defaults.
    options_class: ClassVar[type]
    handles_constraints: ClassVar[bool]
    takes_state_guess: ClassVar[bool]
    takes_duals: ClassVar[bool]
    #: The entries of ``tt.solve``'s ``duals`` it takes (none unless :attr:`takes_duals`).
    dual_entries: ClassVar[tuple] = ()
    starts_from_shifted_states: ClassVar[bool] = False
    kkt_point: ClassVar[bool] = True
    #: Whether its options' ``record`` (:meth:`kernel_options`) replays its expansion from recorded graphs
    #: (:mod:`torchtraj.core.recorded`).
    records: ClassVar[bool] = False
    #: Whether its options' ``compile`` (:meth:`kernel_options`) runs its kernels compiled by ``torch.compile``
    #: (:mod:`torchtraj.core.compiled`); a method without compiled kernels accepts the field (the control-step
    #: interface sets it) and runs eager.
    compiles: ClassVar[bool] = False

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"

    # ------------------------------------------------------------------ options
    def default_options(self):
        """The options of a solve that names none."""
        return self.options_class()

    def options(self, options):
        """``options`` as an :attr:`options_class` instance: ``None`` gives :meth:`default_options`, a dict its
        fields; anything else is a ``TypeError``. Every field is checked (:func:`torchtraj.core.options.validate`:
        types, nested options' classes, positive budgets, non-negative tolerances, positive barriers and
        penalties), a bad one named in a ``ValueError`` or ``TypeError``."""
        cls = self.options_class
        if options is None:
            return self.default_options()
        if isinstance(options, dict):
            unknown = sorted(set(options) - {f.name for f in dataclasses.fields(cls)})
            if unknown:
                raise TypeError(f"options for method {self.name!r}: unknown field(s) {unknown}; {cls.__name__} has "
                                f"{[f.name for f in dataclasses.fields(cls)]}")
            options = cls(**options)
        if not isinstance(options, cls):
            raise TypeError(f"options for method {self.name!r} must be {cls.__name__} or a dict, "
                            f"got {type(options).__name__}")
        validate(options)
        return options

    def kernel_options(self, options):
        """The options whose ``record`` (recorded graphs, :mod:`torchtraj.core.recorded`) and ``compile``
        (:mod:`torchtraj.core.compiled`) say how the method's kernels run: ``options`` themselves, unless the method
        keeps them in nested options (ALTRO: its inner iLQR's)."""
        return options

    def kernel_setting(self, options, name: str, default=None):
        """The field ``name`` (``"record"``, ``"compile"``) of ``options``' :meth:`kernel_options`; ``default`` where
        they have none, or where ``options`` is ``None``."""
        return default if options is None else getattr(self.kernel_options(options), name, default)

    def with_kernels(self, options, **fields):
        """``options`` with the :meth:`kernel_options`' ``fields`` replaced (``record=True``, ``compile=True``)."""
        return dataclasses.replace(options, **fields)

    # ------------------------------------------------------------------ solving
    @abc.abstractmethod
    def solve(self, problem: Problem, batch: Batch, options) -> Solution:
        """Solve the ``batch`` of instances of ``problem`` with ``options`` (an :attr:`options_class` instance).

        ``batch`` is checked and contiguous; its ``X0`` is ``None`` unless :attr:`takes_state_guess`, its
        ``duals`` unless :attr:`takes_duals`."""

    def kkt_problem(self, problem: Problem, options) -> Optional[Problem]:
        """The problem of which a converged solution with ``options`` is a KKT point, where it differs from
        ``problem`` (constrained or not as :attr:`handles_constraints` says); ``None``: it does not differ."""
        return None

    def fixes_initial_state(self, options) -> bool:
        """Whether a solution with ``options`` starts at the given ``x0`` (the KKT certificate then counts the
        initial defect, and the implicit layer, which holds ``x0`` fixed, can differentiate it)."""
        return True

    # ------------------------------------------------------------------ one control step (torchtraj.control.mpc)
    def step_defaults(self):
        """The options of a control step whose controller names none."""
        return self.default_options()

    def step_options(self, options, iterations: Optional[int], compile: bool = False):
        """The options of one control step: ``options`` (default :meth:`step_defaults`) with a budget of
        ``iterations`` iterations (``None``: as given) and, with ``compile``, compiled kernels."""
        opts = self.options(self.step_defaults() if options is None else options)
        if compile:
            opts = self.with_kernels(opts, compile=True)
        return opts if iterations is None else dataclasses.replace(opts, iterations=int(iterations))

    def warm_start(self, U0: Tensor, duals: Optional[dict], X0: Optional[Tensor] = None) -> dict:
        """``tt.solve``'s keyword arguments that start a control step from the shifted controls ``U0 (B, N, nu)``,
        the shifted carried duals (:meth:`carried_duals`; ``None`` when none are carried) and, for a method that
        :attr:`starts_from_shifted_states`, the shifted states ``X0 (B, N+1, nx)`` (``None``: every instance starts
        cold, from the method's own start)."""
        kwargs = {"U0": U0, "duals": duals if self.takes_duals else None}
        if X0 is not None and self.starts_from_shifted_states:
            kwargs["X0"] = X0
        return kwargs

    def start_states(self, problem: Problem, batch: Batch, options) -> Tensor:
        """The states ``(B, N+1, nx)`` that a solve of ``batch`` (no ``X0``) with ``options`` starts from: by default
        the rollout of its controls. A control step asks a method that :attr:`starts_from_shifted_states` for its
        cold instances among warm ones, so that each starts as it would alone."""
        return rollout(problem.dynamics, batch.x0, batch.U0, batch.params)

    def carried_duals(self, constraints: Constraints, solution: Solution, options) -> dict:
        """The duals, as ``tt.solve``'s ``duals`` (entries among :attr:`dual_entries`), that the next control step
        starts from before the shift: by default ``{"multipliers": ...}``, per block as in
        :attr:`Solution.multipliers`; ``{}``: none. Asked only of a method that :attr:`takes_duals`. The controller
        shifts every entry with a knot dimension by one knot and gives a cold instance zeros. ``constraints`` are
        those of ``solution``'s problem, kept by the caller from one step to the next."""
        return {"multipliers": dict(solution.multipliers)}
