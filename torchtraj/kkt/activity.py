r"""Which inequality rows ``g(z) ≤ 0`` a Newton step holds as equalities ``g(z) = 0`` (the *active set*).

The KKT system of :mod:`torchtraj.kkt.newton` takes its held rows as a mask. Each method decides that mask by
its own rule, because each sees a different iterate: an augmented-Lagrangian point whose multipliers are zero or
positive, an interior-point iterate whose multipliers are positive on every row (``z s = μ``), or a candidate
KKT point of a held set. The rules are written here once, each with where it is used and why. All return
boolean masks of the shape of their arguments; the callers restrict them to the knots where a row applies and
convert them to the masks' floating type.

============================================  =====================================================================
rule                                          used by
============================================  =====================================================================
:func:`by_value`                              the implicit layer without a solver's multipliers
:func:`by_value_or_multiplier`                ALTRO's projection (Howell et al. 2019 §III-D)
:func:`by_multiplier_against_slack`           the implicit layer with a solver's multipliers
:func:`multiplier_exceeds_slack`              the IPM crossover's proposed set
:func:`primal_dual_update`                    the IPM crossover's next set (Hintermüller, Ito & Kunisch 2002)
:func:`violated`                              the implicit layer's refinement, rows a step would violate
============================================  =====================================================================
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

#: :func:`by_multiplier_against_slack` holds a row by its multiplier only while ``g > −FAR · tol``.
FAR = 1e3


def by_value(g: Tensor, tol: float) -> Tensor:
    """Rows violated or nearly so, ``g > −tol``.

    The implicit layer's rule where no multipliers are at hand (:func:`torchtraj.differentiation.kkt_system.kkt_system`
    without an imposed set): at a converged solution an active row is at round-off and an inactive one far
    below ``−tol``; a weakly active row (zero multiplier) is held, which gives the one-sided derivative in
    which it stays active."""
    return g > -tol


def by_value_or_multiplier(g: Tensor, dual: Tensor, tol: float) -> Tensor:
    """Rows violated or nearly so, ``g > −tol``, or with a positive multiplier, ``dual > 0``.

    ALTRO's projection (Howell et al. 2019 §III-D): its augmented-Lagrangian multipliers are zero on the rows the
    iterations left inactive (eq. 17 clamps them), so a positive one marks a row that pushed back, however far
    the coarse solution still is from its bound."""
    return (g > -tol) | (dual > 0)


def by_multiplier_against_slack(g: Tensor, dual: Tensor, tol: float) -> Tensor:
    """Rows with ``g > −tol``, or whose multiplier exceeds their slack, ``dual > −g``, while ``g > −FAR · tol``.

    The implicit layer's rule at a solver's point with the solver's multipliers (``Solution.multipliers``).
    Multiplier against slack, not multiplier against zero: an interior-point method's multipliers are positive on
    every row (``z s = μ``), and near a bound both are small, so only which of the two is larger tells an active
    row (``s ≈ μ / z``) from an inactive one (``z ≈ μ / s``); a fixed threshold on the multiplier held rows
    ``1e-3`` inside a bound with ``z ≈ 1e-6``, and refinement then moved ``linear_box`` instances ``1e-3`` away
    to a dearer point. The value guard keeps an ALTRO multiplier left on a row far inside its bound from
    holding it."""
    return (g > -tol) | ((dual > -g) & (g > -FAR * tol))


def multiplier_exceeds_slack(z: Tensor, s: Tensor) -> Tensor:
    """Rows whose multiplier exceeds their slack, ``z > s``: the strict-complementarity indicator.

    The IPM crossover's proposed set (:func:`torchtraj.solvers.ipm.crossover.proposed_active_set`): near a
    solution an active row has ``s ≈ μ / z → 0`` and an inactive one ``z ≈ μ / s → 0``."""
    return z > s


def primal_dual_update(held: Tensor, y: Tensor, s: Tensor, applies: Optional[Tensor] = None) -> Tensor:
    """The primal-dual active-set update (Hintermüller, Ito & Kunisch 2002) of a candidate KKT point of the set
    ``held`` (``> 0`` where held): a held row stays where its multiplier ``y`` is positive, a free one joins where
    the candidate violates it, which its slack ``s = max(−g, 0) = 0`` shows (held rows have ``g = 0``, free ones
    ``y = 0``, so this is ``y + g > 0``); only rows where ``applies`` (default: all) may join.

    The IPM crossover's next set (:func:`torchtraj.solvers.ipm.crossover.next_active_set`)."""
    joins = s == 0 if applies is None else (s == 0) & applies
    return torch.where(held > 0, y > 0, joins)


def violated(held: Tensor, g: Tensor) -> Tensor:
    """Rows outside ``held`` (``== 0``) that ``g > 0`` violates: the rows to add to the set.

    The implicit layer's refinement (:func:`torchtraj.differentiation.refine.refine`): an interior-point solution
    leaves the rows where a bound arc begins or ends at ``z ≈ s ≈ √μ``, which no test on ``z`` and ``s`` alone
    sorts; such a row is held once a Newton step shows that it binds."""
    return (held == 0) & (g > 0)
