r"""The construction probe of a :class:`~torchtraj.Problem`: the user's functions run once as the solvers run them.

Each function (dynamics, costs, constraints) is called

1. directly, on *copies* of ``x0``, ``u_init[0]`` and one instance's parameters: its output must be a finite tensor of
   the documented shape in the problem's dtype, and its inputs must come back unchanged (a function that writes
   into its argument would corrupt the caller's ``x0`` and, inside a solver, the iterates);
2. under ``torch.func.vmap`` of the value and of ``jacrev`` (the derivatives of
   :mod:`torchtraj.core.derivatives`), at four points

   .. math::  (x_1, u_1),\ (x_2, u_2),\ (x_2, u_1),\ (x_1, u_2), \qquad x_2 = x_1 + s\,\xi_x,\ u_2 = u_1 + s\,\xi_u,

   with fixed pseudo-random directions ``ξ`` and ``s = 1 + max |(x_1, u_1)|``. A failure there (``.item()``,
   numpy, an in-place write into a new tensor, a Python ``if`` on a tensor) is raised as a ``ValueError`` that
   names the function and says what to write instead (:func:`explain`).

The second check is made once per function and signature (dtype, sizes, parameter shapes): a problem rebuilt
with other parameter values (``with_params``, ``replace``) skips it.

A Jacobian identically zero at the four points while the value changes with that argument means the graph is cut
(``.detach()``, ``torch.no_grad``, ``.data``, a numpy round trip): the solvers would see no effect of it, so a
``UserWarning`` names the function and the argument. A function that is constant in an argument is not flagged.
"""

from __future__ import annotations

import warnings
import weakref
from typing import Callable

import torch
from torch import Tensor
from torch.func import jacrev, vmap

#: torch.func's messages (their distinctive part) and what to write instead, in the order they are matched.
_ADVICE = (
    ("either (1) calling .item()",
     "it turns a tensor into a Python number (.item(), float(), int(), torch.tensor([...]) of tensor entries) or "
     "branches in Python on a tensor value (if / while / and / or on a tensor); keep values as tensors (torch.stack "
     "or torch.cat instead of torch.tensor([...])) and choose with torch.where instead of if"),
    (".item()",
     "it turns a tensor into a Python number (.item(), float(), int(), or torch.tensor([...]) built from tensor "
     "entries); keep values as tensors: torch.stack / torch.cat instead of torch.tensor([...]), no .item()"),
    ("data-dependent control flow",
     "it branches in Python on a tensor value (if / while / and / or on a tensor); choose with torch.where, "
     "torch.clamp, torch.maximum instead"),
    ("Boolean value of Tensor",
     "it branches in Python on a tensor value (if / while / and / or on a tensor); choose with torch.where, "
     "torch.clamp, torch.maximum instead"),
    ("data pointer",
     "it converts a tensor to numpy (np.array(x), x.numpy(), np.sin(x), ...); use the torch functions "
     "(torch.sin, torch.stack, ...) so that torch.func can batch and differentiate it"),
    ("numpy",
     "it converts a tensor to numpy (np.array(x), x.numpy(), np.sin(x), ...); use the torch functions "
     "(torch.sin, torch.stack, ...) so that torch.func can batch and differentiate it"),
    ("inplace",
     "it writes in place (y[i] = ..., y += ..., torch.zeros(...) then filled in); build the result with "
     "torch.stack / torch.cat / out-of-place arithmetic instead"),
    ("in-place",
     "it writes in place (y[i] = ..., y += ..., torch.zeros(...) then filled in); build the result with "
     "torch.stack / torch.cat / out-of-place arithmetic instead"),
    ("expected scalar type",
     "it mixes dtypes (a constant made in another dtype than the problem's); make constants with dtype=x.dtype"),
    ("dtype",
     "it mixes dtypes (a constant made in another dtype than the problem's); make constants with dtype=x.dtype"),
)


def explain(name: str, exc: Exception) -> ValueError:
    """A ``ValueError`` naming ``Problem.<name>``, translating torch.func's message ``exc`` into what to change."""
    message = str(exc)
    advice = next((text for key, text in _ADVICE if key in message), None)
    head = f"Problem.{name} fails under torch.func.vmap / jacrev, as the solvers evaluate it"
    if advice is None:
        return ValueError(f"{head}: {message.splitlines()[0] if message else type(exc).__name__}")
    return ValueError(f"{head}: {advice} (torch: {message.splitlines()[0][:160]})")


def _copies(x: Tensor, u: Tensor, p: dict):
    return x.clone(), u.clone(), {k: v.clone() for k, v in p.items()}


def _unchanged(before: Tensor, after: Tensor) -> bool:
    return bool(torch.equal(torch.nan_to_num(before), torch.nan_to_num(after)))


def call_once(name: str, fn: Callable, stage: bool, x: Tensor, u: Tensor, p: dict, dtype: torch.dtype) -> Tensor:
    """``fn`` on copies of ``(x, u, p)`` (``(x, p)`` for a state function): a finite tensor in ``dtype``, its inputs
    unchanged; else a ``ValueError`` naming ``Problem.<name>``."""
    xc, uc, pc = _copies(x, u, p)
    try:
        out = fn(xc, uc, pc) if stage else fn(xc, pc)
    except Exception as exc:  # re-raised with the function named
        raise ValueError(f"Problem.{name} failed on a probe call: {exc}") from exc
    changed = [arg for arg, a, b in (("x", x, xc), ("u", u, uc)) if (stage or arg == "x") and not _unchanged(a, b)]
    changed += [f"p[{k!r}]" for k in p if not _unchanged(p[k], pc[k])]
    if changed:
        raise ValueError(f"Problem.{name} writes into its argument(s) {', '.join(changed)} in place (x[i] = ..., "
                         "x += ...); return a new tensor (torch.stack, torch.cat, x + ...) and leave the inputs as "
                         "they are: the solvers pass their iterates, and the caller's x0, to it")
    if not isinstance(out, Tensor):
        raise ValueError(f"Problem.{name} must return a torch.Tensor, got {type(out).__name__}")
    if out.dtype != dtype:
        raise ValueError(f"Problem.{name} returns {out.dtype} in a {dtype} problem (x0's dtype): a constant or a "
                         f"parameter in it is in another dtype (torch.tensor(..., dtype=...), a numpy array, "
                         f"torch.from_numpy); make constants with dtype=x.dtype, or convert the problem with "
                         f"Problem.to(dtype)")
    if not bool(torch.isfinite(out).all()):
        raise ValueError(f"Problem.{name} returned non-finite values at x0, u_init[0]: {out}")
    return out


def _points(x: Tensor, u: Tensor) -> tuple:
    """The four probe points (module docstring): ``X (4, nx)``, ``U (4, nu)``."""
    g = torch.Generator().manual_seed(0)
    scale = 1.0 + float(torch.cat([x, u]).detach().abs().max())
    x2 = x + scale * torch.randn(x.shape, generator=g, dtype=torch.float64).to(x)
    u2 = u + scale * torch.randn(u.shape, generator=g, dtype=torch.float64).to(u)
    return torch.stack([x, x2, x2, x]).detach(), torch.stack([u, u2, u, u2]).detach()


#: ``{function: {signature}}``: the functions already run under torch.func, per signature (module docstring).
_CHECKED: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def check_under_torch_func(name: str, fn: Callable, stage: bool, x: Tensor, u: Tensor, p: dict) -> None:
    """Run ``fn`` and its ``jacrev`` under ``vmap`` at the probe points; a ``ValueError`` (:func:`explain`) where
    torch.func refuses it, a warning where a Jacobian is identically zero but the value is not constant."""
    signature = (name, stage, x.dtype, x.device, x.shape[0], u.shape[0],
                 tuple(sorted((k, tuple(v.shape)) for k, v in p.items())))
    try:
        seen = _CHECKED.setdefault(fn, set())
    except TypeError:  # not weakly referenceable (a builtin): checked every time
        seen = set()
    if signature in seen:
        return
    _check(name, fn, stage, x, u, p)
    seen.add(signature)


def _check(name: str, fn: Callable, stage: bool, x: Tensor, u: Tensor, p: dict) -> None:
    X, U = _points(x, u)
    p = {k: v.detach() for k, v in p.items()}
    if stage:
        f = lambda x_, u_: fn(x_, u_, p)  # noqa: E731
        args, argnums, labels = (X, U), (0, 1), ("x", "u")
    else:
        f = lambda x_: fn(x_, p)  # noqa: E731
        args, argnums, labels = (X,), (0,), ("x",)
    try:
        values = vmap(f)(*args)
        jacobians = vmap(jacrev(f, argnums=argnums))(*args)
    except Exception as exc:
        raise explain(name, exc) from exc
    if not all(bool(torch.isfinite(t).all()) for t in (values, *jacobians)):
        return  # a point outside the function's domain: no conclusion
    # rows 0 and 2 differ in x only, rows 0 and 3 in u only
    other = {"x": 2, "u": 3}
    cut = [label for label, jac in zip(labels, jacobians)
           if not bool(jac.any()) and not bool(torch.equal(values[0], values[other[label]]))]
    if cut:
        what = " and ".join(cut)
        warnings.warn(f"Problem.{name}: its value changes with {what} but its Jacobian with respect to {what} is "
                      "identically zero at four probe points: the graph is cut (.detach(), torch.no_grad(), .data, "
                      "a numpy round trip or torch.tensor(...) of values), so the solvers see no effect of "
                      f"{what}; compute it with differentiable torch operations", UserWarning, stacklevel=4)


def probe(problem) -> dict:
    """Check every function of ``problem`` (a :class:`~torchtraj.Problem`, which calls this from its constructor:
    module docstring); return the rows of each constraint function."""
    nx, dtype = problem.nx, problem.dtype
    x, u, p = problem.x0.detach(), problem.u_init[0].detach(), problem.instance_params()
    out = call_once("dynamics", problem.dynamics, True, x, u, p, dtype)
    if out.shape != (nx,):
        raise ValueError(f"Problem.dynamics must return shape ({nx},) for x of shape ({nx},), got {tuple(out.shape)}")
    check_under_torch_func("dynamics", problem.dynamics, True, x, u, p)
    for name, stage in (("stage_cost", True), ("terminal_cost", False)):
        out = call_once(name, getattr(problem, name), stage, x, u, p, dtype)
        if out.shape != ():
            raise ValueError(f"Problem.{name} must return a scalar (shape ()), got {tuple(out.shape)}")
        check_under_torch_func(name, getattr(problem, name), stage, x, u, p)
    sizes = {}
    for name in ("stage_eq", "stage_ineq", "state_ineq", "terminal_eq", "terminal_ineq"):
        fn = getattr(problem, name)
        sizes[name] = 0
        if fn is None:
            continue
        stage = name.startswith("stage")
        out = call_once(name, fn, stage, x, u, p, dtype)
        if out.dim() != 1:
            raise ValueError(f"Problem.{name} must return a vector (m,), got shape {tuple(out.shape)}")
        sizes[name] = int(out.shape[0])
        if sizes[name]:
            check_under_torch_func(name, fn, stage, x, u, p)
    return sizes


def _outputs(problem, p: dict) -> list:
    """The shapes and dtypes of every function's output at ``x0``, ``u_init[0]`` and parameters ``p``; ``None``
    where a function fails."""
    x, u = problem.x0.detach(), problem.u_init[0].detach()
    out = []
    for name in ("dynamics", "stage_cost", "terminal_cost", "stage_eq", "stage_ineq", "state_ineq", "terminal_eq",
                 "terminal_ineq"):
        fn = getattr(problem, name)
        if fn is None:
            continue
        xc, uc, pc = _copies(x, u, p)
        try:
            value = fn(xc, uc, pc) if name in ("dynamics", "stage_cost", "stage_eq", "stage_ineq") else fn(xc, pc)
        except Exception:  # noqa: BLE001 (any failure means: not this shape)
            return None
        if not isinstance(value, Tensor):
            return None
        out.append((tuple(value.shape), value.dtype))
    return out


def accepts_one_row(problem, name: str) -> bool:
    """Whether every function of ``problem`` runs, with outputs of the same shapes, when the parameter ``name`` is
    replaced by its first row: then its shape does not tell one instance's value from one value per instance
    (:func:`torchtraj.core.batch.check_parameter_batch`). Remembered per problem."""
    cache = problem.__dict__.setdefault("_accepts_one_row", {})
    if name not in cache:
        p = problem.instance_params()
        full = _outputs(problem, p)
        row = _outputs(problem, {**p, name: p[name][0]})
        cache[name] = full is not None and row == full
    return cache[name]
