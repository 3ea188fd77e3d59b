"""Integrators: combinators that turn continuous dynamics into a discrete step.

Given continuous dynamics ``xdot = f(x, u, p)`` and a step ``dt``, each combinator
returns ``step(x, u, p) -> x_next`` with the control held constant over the step
(zero-order hold), as in the problem set:

* explicit Euler:  x+ = x + dt f(x, u)
* classic RK4:     k1 = f(x, u), k2 = f(x + dt/2 k1, u), k3 = f(x + dt/2 k2, u),
                   k4 = f(x + dt k3, u),  x+ = x + dt/6 (k1 + 2 k2 + 2 k3 + k4)

``dt`` may be a float or the name of a parameter in ``p`` (so a time-penalised
problem or a learned step can change it per instance).
"""

from __future__ import annotations

from typing import Callable, Mapping, Union

from torch import Tensor

Dynamics = Callable[[Tensor, Tensor, Mapping[str, Tensor]], Tensor]
StepSize = Union[float, str]


def _step_size(dt: StepSize, p: Mapping[str, Tensor]):
    return p[dt] if isinstance(dt, str) else dt


def euler(f: Dynamics, dt: StepSize) -> Dynamics:
    """Explicit Euler step of ``f`` with step ``dt`` (a float or a parameter name)."""

    def step(x: Tensor, u: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        h = _step_size(dt, p)
        return x.add(f(x, u, p), alpha=h) if not isinstance(h, Tensor) else x + h * f(x, u, p)

    step.__name__ = f"euler({getattr(f, '__name__', 'f')})"
    return step


def rk4(f: Dynamics, dt: StepSize) -> Dynamics:
    """Classic fourth-order Runge-Kutta step of ``f`` with step ``dt`` (a float or a parameter name)."""

    def step(x: Tensor, u: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        h = _step_size(dt, p)
        if not isinstance(h, Tensor):  # a number: each axpy is one fused call (``torch.add``'s ``alpha``)
            k1 = f(x, u, p)
            k2 = f(x.add(k1, alpha=0.5 * h), u, p)
            k3 = f(x.add(k2, alpha=0.5 * h), u, p)
            k4 = f(x.add(k3, alpha=h), u, p)
            return x.add(k1.add(k2, alpha=2.0).add(k3, alpha=2.0).add(k4), alpha=h / 6.0)
        k1 = f(x, u, p)
        k2 = f(x + 0.5 * h * k1, u, p)
        k3 = f(x + 0.5 * h * k2, u, p)
        k4 = f(x + h * k3, u, p)
        return x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

    step.__name__ = f"rk4({getattr(f, '__name__', 'f')})"
    return step
