"""The constraints of a problem gathered into stage and terminal blocks.

Every solver sees the constraints of a :class:`~torchtraj.Problem` in one layout:

* stage equalities   ``h_k(x, u) = 0``  (``stage_eq``),                         k = 0..N-1
* stage inequalities ``g_k(x, u) <= 0`` stacked from the blocks
  ``stage_ineq``, ``u_upper`` (u - u_max), ``u_lower`` (u_min - u), ``state_ineq``,
  ``x_upper`` (x - x_max), ``x_lower`` (x_min - x), only the finite bounds;
  the state blocks are switched off at knot 0 by a row mask (x_0 is fixed),
* terminal equalities ``h_N(x) = 0`` and inequalities ``g_N(x) <= 0``.

:class:`Constraints` records which rows belong to which named block, so solutions can
report multipliers per block.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from .batching import concat, map_stage, map_state
from .problem import Problem

STAGE_INEQ_BLOCKS = ("stage_ineq", "u_upper", "u_lower", "state_ineq", "x_upper", "x_lower")
STATE_BLOCKS = ("state_ineq", "x_upper", "x_lower")


@dataclass(frozen=True)
class _Rows:
    """The finite entries of a bound vector: ``index`` (a slice, or a long tensor on the bound's device) and
    their ``count``."""

    index: object
    count: int

    def __len__(self) -> int:
        return self.count


@dataclass
class ConstraintValues:
    """Constraint values at a trajectory: ``eq (B, N, me)``, ``ineq (B, N, mi)``,
    ``eqN (B, meN)``, ``ineqN (B, miN)``; masked-off inequality rows hold ``-inf``."""

    eq: Tensor
    ineq: Tensor
    eqN: Tensor
    ineqN: Tensor

    def max_violation(self) -> Tensor:
        """Largest violation ``(B,)``: ``|h|`` for equalities, ``max(g, 0)`` for inequalities."""
        B = self.eq.shape[0]
        parts = [self.eq.new_zeros(B, 1),  # no constraint: no violation
                 self.eq.abs().reshape(B, -1), self.ineq.clamp_min(0).reshape(B, -1),
                 self.eqN.abs().reshape(B, -1), self.ineqN.clamp_min(0).reshape(B, -1)]
        return torch.cat(parts, -1).amax(-1)


class Constraints:
    """Stage and terminal constraint functions of ``problem`` in the solver layout; none with ``ignored`` (the
    KKT conditions of a method that ignores them).

    Made on the host (the bounds' finite entries are read there), so outside CUDA graphs: a graphed kernel takes
    them as an argument, and its graph makes them again from ``graph_rebuilt_from`` (:mod:`torchtraj.core.graphs`)."""

    graph_rebuilt_from = ("problem", "ignored")
    #: Its tensors are made once and never replaced, so a recorded kernel may hold them (:mod:`~.recorded`).
    RECORDED_OWNER = True

    @classmethod
    def of(cls, problem: Problem, ignored: bool = False) -> "Constraints":
        """The layout of ``problem``'s constraints, made once per problem object and kept on it: every solver, the
        implicit layer and MPC share it instead of reading the bounds again (a host synchronisation each)."""
        return problem.derived("_constraints", ignored, lambda: cls(problem, ignored))

    def __init__(self, problem: Problem, ignored: bool = False):
        self.problem = problem
        self.ignored = ignored
        sizes = problem.constraint_sizes()
        self.u_upper_idx = self._finite(problem.u_upper)
        self.u_lower_idx = self._finite(problem.u_lower)
        self.x_upper_idx = self._finite(problem.x_upper)
        self.x_lower_idx = self._finite(problem.x_lower)
        counts = {
            "stage_ineq": sizes["stage_ineq"],
            "u_upper": len(self.u_upper_idx), "u_lower": len(self.u_lower_idx),
            "state_ineq": sizes["state_ineq"],
            "x_upper": len(self.x_upper_idx), "x_lower": len(self.x_lower_idx),
        }
        self.ineq_blocks = {}
        start = 0
        for name in STAGE_INEQ_BLOCKS:
            self.ineq_blocks[name] = slice(start, start + counts[name])
            start += counts[name]
        self.me, self.mi = sizes["stage_eq"], start
        self.meN, self.miN = sizes["terminal_eq"], sizes["terminal_ineq"]
        knot_mask = torch.ones(problem.N, self.mi, dtype=problem.dtype, device=problem.device)
        for name in STATE_BLOCKS:
            knot_mask[0, self.ineq_blocks[name]] = 0.0
        #: ``(N, mi)``: 1 where a stage inequality row applies at knot k.
        self.ineq_knot_mask = knot_mask
        #: the number of ones in it (the state rows do not apply at knot 0), known without reading the device
        self.applied_ineq_rows = self.mi * problem.N - sum(counts[name] for name in STATE_BLOCKS)
        #: ``(mi,)``: the share of its constraint that a stage inequality row is, ½ for the two rows of a variable
        #: bounded on both sides (one constraint ``l ≤ v ≤ u``, as an NLP solver's row with its two bounds), else 1.
        self.ineq_share = torch.ones(self.mi, dtype=problem.dtype, device=problem.device)
        for upper, lower in (("u_upper", "u_lower"), ("x_upper", "x_lower")):
            entries = {name: self._finite_list(getattr(problem, name)) for name in (upper, lower)}
            both = set(entries[upper]) & set(entries[lower])
            for name, finite in entries.items():
                start = self.ineq_blocks[name].start
                for row, entry in enumerate(finite):
                    if entry in both:
                        self.ineq_share[start + row] = 0.5
        if ignored:
            self.me = self.mi = self.meN = self.miN = self.applied_ineq_rows = 0
        self._bound_selection = self._bound_selection_of_rows()

    @staticmethod
    def _finite_list(bound) -> list:
        """The indices of the finite entries of ``bound`` (``None``: none)."""
        return [] if bound is None else [i for i, v in enumerate(bound.tolist()) if abs(v) != float("inf")]

    @staticmethod
    def _finite(bound):
        """Entries of ``bound`` that are finite: a slice when they are contiguous (a view), else an index tensor
        on the bound's device (a Python list would be copied to the device at every call)."""
        rows = Constraints._finite_list(bound)
        if not rows:
            return _Rows(slice(0, 0), 0)
        if rows == list(range(rows[0], rows[-1] + 1)):
            return _Rows(slice(rows[0], rows[-1] + 1), len(rows))
        return _Rows(torch.tensor(rows, dtype=torch.long, device=bound.device), len(rows))

    def bound_rows(self):
        """``(mi, nu)``: where every constraint row is a control bound, the rows' signed selection ``∂g/∂u`` (``+1`` on
        the ``u_upper`` rows, ``−1`` on the ``u_lower`` ones; :attr:`torchtraj.riccati.LQR.bounds`); else ``None``."""
        return self._bound_selection

    def _bound_selection_of_rows(self):
        upper, lower = self.u_upper_idx, self.u_lower_idx
        if self.me or self.meN or self.miN or not self.mi or self.mi != len(upper) + len(lower):
            return None
        prob = self.problem
        controls = torch.arange(prob.nu, device=prob.device)
        selection = torch.zeros(self.mi, prob.nu, dtype=prob.dtype, device=prob.device)
        for start, rows, sign in ((0, upper, 1.0), (len(upper), lower, -1.0)):
            if len(rows):
                selection[torch.arange(start, start + len(rows), device=prob.device), controls[rows.index]] = sign
        return selection

    @property
    def back_propagated(self) -> bool:
        """Whether the Riccati core takes these rows, held as equalities, by its constraint back-propagation (an SVD
        a stage, whose error check reads the device: no CUDA graph), rather than as declared control bounds."""
        return not self.empty and self.bound_rows() is None

    @property
    def empty(self) -> bool:
        return self.me + self.mi + self.meN + self.miN == 0

    # per-instance functions (vmapped and differentiated by the solvers)
    def stage_eq(self, x: Tensor, u: Tensor, p) -> Tensor:
        if self.problem.stage_eq is None:
            return x.new_zeros(0)
        return self.problem.stage_eq(x, u, p)

    def stage_ineq(self, x: Tensor, u: Tensor, p) -> Tensor:
        prob = self.problem
        parts = []
        if prob.stage_ineq is not None:
            parts.append(prob.stage_ineq(x, u, p))
        if self.u_upper_idx:
            parts.append(u[self.u_upper_idx.index] - prob.u_upper[self.u_upper_idx.index])
        if self.u_lower_idx:
            parts.append(prob.u_lower[self.u_lower_idx.index] - u[self.u_lower_idx.index])
        if prob.state_ineq is not None:
            parts.append(prob.state_ineq(x, p))
        if self.x_upper_idx:
            parts.append(x[self.x_upper_idx.index] - prob.x_upper[self.x_upper_idx.index])
        if self.x_lower_idx:
            parts.append(prob.x_lower[self.x_lower_idx.index] - x[self.x_lower_idx.index])
        return concat(parts) if parts else x.new_zeros(0)

    def terminal_eq(self, x: Tensor, p) -> Tensor:
        return x.new_zeros(0) if self.problem.terminal_eq is None else self.problem.terminal_eq(x, p)

    def terminal_ineq(self, x: Tensor, p) -> Tensor:
        return x.new_zeros(0) if self.problem.terminal_ineq is None else self.problem.terminal_ineq(x, p)

    # batched evaluation
    def evaluate(self, X: Tensor, U: Tensor, params) -> ConstraintValues:
        """All constraint values at ``X (B, N+1, nx)``, ``U (B, N, nu)``."""
        B, N = U.shape[0], U.shape[1]
        Xs = X[:, :-1]
        eq = map_stage(self.stage_eq, Xs, U, params) if self.me else X.new_zeros(B, N, 0)
        ineq = self._off_knots_ignored(map_stage(self.stage_ineq, Xs, U, params)) if self.mi else X.new_zeros(B, N, 0)
        eqN = map_state(self.terminal_eq, X[:, -1], params) if self.meN else X.new_zeros(B, 0)
        ineqN = map_state(self.terminal_ineq, X[:, -1], params) if self.miN else X.new_zeros(B, 0)
        return ConstraintValues(eq=eq, ineq=ineq, eqN=eqN, ineqN=ineqN)

    def max_violation(self, X: Tensor, U: Tensor, params) -> Tensor:
        """Largest constraint violation ``(B,)`` of the trajectory (zero when there are no constraints)."""
        if self.empty:
            return X.new_zeros(X.shape[0])
        return self.evaluate(X, U, params).max_violation()

    def max_violation_of(self, h: Tensor, g: Tensor, hN: Tensor, gN: Tensor) -> Tensor:
        """:meth:`max_violation` from the rows' values at the trajectory, unmasked ``(B, N, me)``, ``(B, N, mi)``,
        ``(B, meN)``, ``(B, miN)`` (:func:`~torchtraj.core.one_pass.problem_values`'s): the same numbers."""
        if self.empty:
            return h.new_zeros(h.shape[0])
        ineq = self._off_knots_ignored(g) if self.mi else g
        return ConstraintValues(eq=h, ineq=ineq, eqN=hN, ineqN=gN).max_violation()

    def _off_knots_ignored(self, ineq: Tensor) -> Tensor:
        """Stage inequality values ``(B, N, mi)`` with the rows that do not apply at a knot set to ``-inf``."""
        return torch.where(self.ineq_knot_mask > 0, ineq, torch.full_like(ineq, -float("inf")))

    def split_ineq(self, values: Tensor) -> dict:
        """``{block: values[..., rows]}`` for a stage-inequality tensor ``(..., mi)``."""
        return {name: values[..., rows] for name, rows in self.ineq_blocks.items() if rows.stop > rows.start}


def multiplier_blocks(constraints: Constraints, stage: Tensor, terminal: Tensor) -> dict:
    """Stacked ``(B, N, mi + me)`` / ``(B, miN + meN)`` duals split into named blocks."""
    c = constraints
    out = {name: v for name, v in c.split_ineq(stage[..., :c.mi]).items()}
    if c.me:
        out["stage_eq"] = stage[..., c.mi:]
    if c.miN:
        out["terminal_ineq"] = terminal[..., :c.miN]
    if c.meN:
        out["terminal_eq"] = terminal[..., c.miN:]
    return out


def stack_blocks(constraints: Constraints, blocks: dict, fill: float, like: Tensor):
    """Inverse of :func:`multiplier_blocks`: per-block tensors (missing ones filled) → stacked layout."""
    c = constraints
    B, N = like.shape[0], c.problem.N

    def get(name, shape):
        value = blocks.get(name)
        if value is None:
            return like.new_full(shape, fill)
        return torch.as_tensor(value, dtype=like.dtype, device=like.device).expand(shape)

    parts = [get(name, (B, N, rows.stop - rows.start)) for name, rows in c.ineq_blocks.items()]
    stage = torch.cat(parts + [get("stage_eq", (B, N, c.me))], -1)
    terminal = torch.cat([get("terminal_ineq", (B, c.miN)), get("terminal_eq", (B, c.meN))], -1)
    return stage, terminal


#: The entries of a warm start of the multipliers (``tt.solve``'s ``duals``); each method takes some of them
#: (:attr:`~torchtraj.solvers.base.Solver.dual_entries`).
DUAL_ENTRIES = ("multipliers", "penalties", "costate", "barrier")


def map_duals(duals: dict, change: Callable) -> dict:
    """``duals`` (``tt.solve``'s: entries of tensors, or of dicts of per-block tensors) with ``change`` applied to
    every tensor; any other value is kept as it is."""
    return {k: map_duals(v, change) if isinstance(v, dict) else change(v) if isinstance(v, Tensor) else v
            for k, v in duals.items()}


def check_duals(constraints: Constraints, duals: dict, batch: int, entries: tuple = DUAL_ENTRIES,
                method: str = "") -> None:
    """A clear error for a warm start ``duals`` that does not fit ``constraints``: an entry that is not among
    ``entries`` (those ``method`` takes; listed), an unknown block name (the valid ones listed), a block whose shape
    does not broadcast to ``(B, N, rows)`` (stage) or ``(B, rows)`` (terminal), a costate not broadcasting to
    ``(B, N+1, nx)``, a barrier not broadcasting to ``(B,)``."""
    if not isinstance(duals, dict):
        raise TypeError(f"duals must be a dict with entries among {entries}, got {type(duals).__name__}")
    unknown = sorted(set(duals) - set(entries))
    if unknown:
        owner = f"method {method!r} takes" if method else "the valid ones are"
        raise ValueError(f"duals has unknown entries {unknown}; {owner} {list(entries)}")
    c, prob = constraints, constraints.problem
    shapes = {name: (batch, prob.N, rows.stop - rows.start) for name, rows in c.ineq_blocks.items()
              if rows.stop > rows.start}
    for name, m, stage in (("stage_eq", c.me, True), ("terminal_ineq", c.miN, False), ("terminal_eq", c.meN, False)):
        if m:
            shapes[name] = (batch, prob.N, m) if stage else (batch, m)
    for entry in ("multipliers", "penalties"):
        blocks = duals.get(entry) or {}
        if not isinstance(blocks, dict):
            raise TypeError(f"duals[{entry!r}] must be a dict of per-block tensors, got {type(blocks).__name__}")
        wrong = sorted(set(blocks) - set(shapes))
        if wrong:
            raise ValueError(f"duals[{entry!r}] names unknown constraint block(s) {wrong}; this problem's blocks "
                             f"are {sorted(shapes)}")
        for name, value in blocks.items():
            _check_dual(f"duals[{entry!r}][{name!r}]", value, shapes[name])
    if duals.get("costate") is not None:
        _check_dual("duals['costate']", duals["costate"], (batch, prob.N + 1, prob.nx), "(B, N+1, nx)")
    if duals.get("barrier") is not None:
        _check_dual("duals['barrier']", duals["barrier"], (batch,), "(B,): one barrier parameter per instance")


def _check_dual(where: str, value, shape: tuple,
                hint: str = "(B, N, rows) / (B, rows): one value per knot and row, as Solution.multipliers holds them"
                ) -> None:
    # shapes only: the values are not read (no host synchronisation in a control loop's warm starts)
    value = value if isinstance(value, Tensor) else torch.as_tensor(value)
    try:
        fits = torch.broadcast_shapes(tuple(value.shape), shape) == shape
    except RuntimeError:
        fits = False
    if not fits:
        raise ValueError(f"{where} has shape {tuple(value.shape)}, which does not broadcast to {shape} {hint}")
