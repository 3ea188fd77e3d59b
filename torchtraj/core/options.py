"""Validation of a method's options dataclass, one set of rules for every method.

Every method's options are a dataclass whose defaults are its paper's. :func:`validate` checks an instance against
its defaults and against rules read from the field names, so that a solver's options file needs no checks of its
own and a new method is checked as soon as it names its fields as the others do:

* a field's value has its declared type: a ``bool`` for ``bool``, an integer (not a ``bool``) for ``int``, a real
  number for ``float``; a number is never NaN; a nested options object is an instance of its default's class
  (checked in turn). Other declared types (optional numbers, callables, unions) are not type-checked, but a number
  given to them follows the rules below;
* iteration budgets and counts (``iterations``, ``iterations_*``, ``*_steps``, ``*_attempts``, ``segments``,
  ``filter_size``, ``per_round``) are at least 1; a stage's budget (``*_iterations``) at least 0 (0 skips it);
* tolerances (``*tolerance*``) are at least 0; barriers (``barrier_*``), penalties (``penalty_*``), limits
  (``*_max``, ``max_*``), a warm start's floors (``warm_start_*``) and the other positive constants below are
  above 0;
* decrease factors (``*_decrease``, ``backtracking``, ``fraction_to_boundary``) lie in (0, 1) and increase factors
  (``*_increase*``, ``penalty_scaling``) above 1.

A violation is a ``ValueError`` naming the options class, the field, the rule and the value.
"""

from __future__ import annotations

import dataclasses
import math
import numbers


def _counts(name: str) -> bool:
    return (name == "iterations" or name.startswith("iterations_") or name.endswith("_steps")
            or name.endswith("_attempts") or name in ("segments", "filter_size", "per_round"))


def _rule(name: str):
    """``(description, test)`` of the numeric rule that the field ``name`` follows, or ``None``."""
    if _counts(name):
        return "an integer >= 1", lambda v: v >= 1
    if name.endswith("_iterations"):  # a stage's budget: 0 skips the stage
        return "an integer >= 0", lambda v: v >= 0
    if name.endswith("_decrease") or name in ("backtracking", "fraction_to_boundary"):
        return "in (0, 1)", lambda v: 0 < v < 1
    if "_increase" in name or name == "penalty_scaling":
        return "> 1", lambda v: v > 1
    if "tolerance" in name:
        return ">= 0", lambda v: v >= 0
    if (name.startswith(("barrier_", "penalty_", "max_", "warm_start_")) or name.endswith("_max")
            or name in ("slack_cost", "dual_initial", "bound_push")):
        return "> 0", lambda v: v > 0
    if name.startswith("regularization"):
        return ">= 0", lambda v: v >= 0
    return None


def validate(options, owner: str = "") -> None:
    """Check the dataclass ``options`` by the rules of the module docstring; ``owner`` prefixes nested names."""
    cls = type(options)
    defaults = cls()
    prefix = owner or cls.__name__
    for f in dataclasses.fields(options):
        value, default = getattr(options, f.name), getattr(defaults, f.name)
        where = f"{prefix}.{f.name}"
        if dataclasses.is_dataclass(default):
            if type(value) is not type(default):
                raise TypeError(f"{where} must be an instance of {type(default).__name__}, got {type(value).__name__}")
            validate(value, where)
            continue
        if value is None:
            continue
        declared = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", "")
        if declared == "bool":
            if not isinstance(value, bool):
                raise TypeError(f"{where} must be True or False, got {value!r}")
            continue
        if declared in ("int", "float") and not (isinstance(value, numbers.Real) and not isinstance(value, bool)
                                                 and (declared == "float" or isinstance(value, numbers.Integral))):
            kind = "an int" if declared == "int" else "a number"
            raise TypeError(f"{where} must be {kind}, got {value!r} ({type(value).__name__})")
        if isinstance(value, numbers.Real) and not isinstance(value, bool):
            # an optional number (default None) follows its name's rule as well
            if math.isnan(value):
                raise ValueError(f"{where} is NaN")
            rule = _rule(f.name)
            if rule is not None and not rule[1](value):
                raise ValueError(f"{where} must be {rule[0]}, got {value!r}")
