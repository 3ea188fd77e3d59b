"""Continuous-time models of the benchmark problem set, written in torch ops only.

A :class:`Model` carries per-instance continuous dynamics ``xdot = f(x, u, p)``
(``x: (nx,)``, ``u: (nu,)``, ``p`` a dict of 0-dim tensors) and its default physical
parameters. The functions use no ``.item()``, no in-place ops and no Python branches on
values, so they compose with ``torch.func.vmap`` / ``jacrev`` / ``jacfwd`` / ``hessian``,
and parameters such as ``p["mass"]`` can be learned. :meth:`Model.discrete` turns the
model into the step ``x_next = F(x, u, p)`` of :mod:`torchtraj.integrators`.

Models (θ = 0 hangs down for the pendulum, cart-pole and acrobot)::

    double integrator  x = [p, v],            u = [a]:    [v, a]
    pendulum           x = [θ, ω],            u = [τ]:    [ω, (τ − m g l sinθ − b ω) / (m l²)]
    cart-pole          x = [x, θ, ẋ, θ̇],      u = [F]:    H q̈ = −(C q̇ + G − [F, 0]),
                       H = [[mc+mp, mp l cθ], [mp l cθ, mp l²]], C q̇ = [−mp l θ̇² sθ, 0],
                       G = [0, mp g l sθ]; closed form with D = mc + mp sθ²:
                       ẍ = (F + mp sθ (l θ̇² + g cθ)) / D,
                       θ̈ = −(F cθ + mp l θ̇² sθ cθ + (mc+mp) g sθ) / (l D)
    unicycle           x = [x, y, θ],         u = [v, ω]: [v cosθ, v sinθ, ω]
    planar quadrotor   x = [x, y, θ, ẋ, ẏ, θ̇], u = [u1, u2]:
                       [ẋ, ẏ, θ̇, (u1+u2) sinθ / m, (u1+u2) cosθ / m − g, (ℓ/2)(u2 − u1) / J],
                       J = 0.2 m ℓ²
    acrobot            x = [q1, q2, q̇1, q̇2],  u = [τ2]: M(q) q̈ + C(q, q̇) q̇ = τ_g(q) + [0, τ2]
                       (Spong 1995; Tedrake, Underactuated Robotics §3.2), see :func:`acrobot`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping, Union

import torch
from torch import Tensor

from . import integrators

Params = Mapping[str, Tensor]
ContinuousDynamics = Callable[[Tensor, Tensor, Params], Tensor]
StepFn = Callable[[Tensor, Tensor, Params], Tensor]

_INTEGRATORS = {"rk4": integrators.rk4, "euler": integrators.euler}


@dataclass(frozen=True, eq=False)
class Model:
    """A continuous-time model ``xdot = dynamics(x, u, p)``.

    Args:
        name: registry name.
        nx, nu: state and control dimensions.
        dynamics: ``(x (nx,), u (nu,), p) -> xdot (nx,)`` in torch ops only.
        params: default physical parameters, 0-dim float64 tensors by name.
        state_names, control_names: labels of the state and control components.
    """

    name: str
    nx: int
    nu: int
    dynamics: ContinuousDynamics
    params: dict[str, Tensor]
    state_names: tuple[str, ...]
    control_names: tuple[str, ...]

    def discrete(self, dt: Union[float, str], integrator: str = "rk4") -> StepFn:
        """The discrete step ``(x, u, p) -> x_next`` over ``dt`` (a float or a parameter name)."""
        if integrator not in _INTEGRATORS:
            raise ValueError(f"integrator must be one of {sorted(_INTEGRATORS)}, got {integrator!r}")
        return _INTEGRATORS[integrator](self.dynamics, dt)


def _params(**values: float) -> dict[str, Tensor]:
    return {k: torch.tensor(float(v), dtype=torch.float64) for k, v in values.items()}


# --------------------------------------------------------------------- double integrator
def _double_integrator(x: Tensor, u: Tensor, p: Params) -> Tensor:
    return torch.stack([x[1], u[0]])


def double_integrator() -> Model:
    """A unit mass on a line: ``x = [p, v]``, ``u = [a]``, ``xdot = [v, a]``; no parameters."""
    return Model("double_integrator", 2, 1, _double_integrator, {}, ("p", "v"), ("a",))


# ------------------------------------------------------------------------------ pendulum
def _pendulum(x: Tensor, u: Tensor, p: Params) -> Tensor:
    m, l, b, g = p["mass"], p["length"], p["damping"], p["gravity"]
    theta, omega = x[0], x[1]
    alpha = (u[0] - m * g * l * torch.sin(theta) - b * omega) / (m * l * l)
    return torch.stack([omega, alpha])


def pendulum(mass: float = 1.0, length: float = 0.5, damping: float = 0.1, gravity: float = 9.81) -> Model:
    """A point mass ``mass`` at distance ``length`` with viscous joint ``damping``; θ = 0 hangs down.

    The defaults give the problem set's ``[ω, τ/0.25 − 9.81 sinθ/0.5 − 0.1 ω/0.25]``.
    """
    params = _params(mass=mass, length=length, damping=damping, gravity=gravity)
    return Model("pendulum", 2, 1, _pendulum, params, ("theta", "omega"), ("tau",))


# ------------------------------------------------------------------------------ cartpole
def _cartpole(x: Tensor, u: Tensor, p: Params) -> Tensor:
    mc, mp, l, g = p["cart_mass"], p["pole_mass"], p["pole_length"], p["gravity"]
    theta, v, omega, force = x[1], x[2], x[3], u[0]
    s, c = torch.sin(theta), torch.cos(theta)
    denom = mc + mp * s * s
    accel = (force + mp * s * (l * omega * omega + g * c)) / denom
    alpha = -(force * c + mp * l * omega * omega * s * c + (mc + mp) * g * s) / (l * denom)
    return torch.stack([v, omega, accel, alpha])


def cartpole(cart_mass: float = 1.0, pole_mass: float = 0.2, pole_length: float = 0.5, gravity: float = 9.81) -> Model:
    """A cart on a rail with a pole of point mass ``pole_mass`` at ``pole_length``; θ = 0 hangs down.

    ``x = [x, θ, ẋ, θ̇]``, ``u = [F]`` (horizontal force on the cart); the problem set's manipulator
    equations solved in closed form (module docstring).
    """
    params = _params(cart_mass=cart_mass, pole_mass=pole_mass, pole_length=pole_length, gravity=gravity)
    return Model("cartpole", 4, 1, _cartpole, params, ("x", "theta", "xdot", "thetadot"), ("force",))


# ------------------------------------------------------------------------------ unicycle
def _unicycle(x: Tensor, u: Tensor, p: Params) -> Tensor:
    theta = x[2]
    return torch.stack([u[0] * torch.cos(theta), u[0] * torch.sin(theta), u[1]])


def unicycle() -> Model:
    """The kinematic (Dubins) car: ``x = [x, y, θ]``, ``u = [v, ω]``; no parameters."""
    return Model("unicycle", 3, 2, _unicycle, {}, ("x", "y", "theta"), ("v", "omega"))


# --------------------------------------------------------------------------- quadrotor2d
def _quadrotor2d(x: Tensor, u: Tensor, p: Params) -> Tensor:
    m, arm, g = p["mass"], p["arm_length"], p["gravity"]
    inertia = 0.2 * m * arm * arm
    theta = x[2]
    thrust = u[0] + u[1]
    return torch.stack([
        x[3],
        x[4],
        x[5],
        thrust * torch.sin(theta) / m,
        thrust * torch.cos(theta) / m - g,
        0.5 * arm * (u[1] - u[0]) / inertia,
    ])


def quadrotor2d(mass: float = 1.0, arm_length: float = 0.3, gravity: float = 9.81) -> Model:
    """A planar quadrotor with two rotor thrusts; ``J = 0.2 m ℓ²``.

    ``x = [x, y, θ, ẋ, ẏ, θ̇]``, ``u = [u1, u2]``; thrusts act along the body axis tilted by θ
    from vertical, with moment arm ``ℓ/2``.
    """
    params = _params(mass=mass, arm_length=arm_length, gravity=gravity)
    names = ("x", "y", "theta", "xdot", "ydot", "thetadot")
    return Model("quadrotor2d", 6, 2, _quadrotor2d, params, names, ("u1", "u2"))


# ------------------------------------------------------------------------------- acrobot
def _acrobot(x: Tensor, u: Tensor, p: Params) -> Tensor:
    m1, m2, l1 = p["link_mass_1"], p["link_mass_2"], p["link_length_1"]
    lc1, lc2, g = p["link_com_1"], p["link_com_2"], p["gravity"]
    # moments of inertia about the joints
    i1 = p["link_inertia_1"] + m1 * lc1 * lc1
    i2 = p["link_inertia_2"] + m2 * lc2 * lc2
    q1, q2, dq1, dq2 = x[0], x[1], x[2], x[3]
    s1, s2, c2, s12 = torch.sin(q1), torch.sin(q2), torch.cos(q2), torch.sin(q1 + q2)
    h = m2 * l1 * lc2
    m11 = i1 + i2 + m2 * l1 * l1 + 2.0 * h * c2
    m12 = i2 + h * c2
    m22 = i2
    # right-hand side tau_g + B u - C qdot
    r1 = -m1 * g * lc1 * s1 - m2 * g * (l1 * s1 + lc2 * s12) + h * s2 * (2.0 * dq1 * dq2 + dq2 * dq2)
    r2 = -m2 * g * lc2 * s12 - h * s2 * dq1 * dq1 + u[0]
    det = m11 * m22 - m12 * m12
    ddq1 = (m22 * r1 - m12 * r2) / det
    ddq2 = (m11 * r2 - m12 * r1) / det
    return torch.stack([dq1, dq2, ddq1, ddq2])


def acrobot(
    link_mass_1: float = 1.0,
    link_mass_2: float = 1.0,
    link_length_1: float = 1.0,
    link_com_1: float = 0.5,
    link_com_2: float = 1.0,
    link_inertia_1: float = 1.0 / 12.0,
    link_inertia_2: float = 1.0 / 3.0,
    gravity: float = 9.81,
) -> Model:
    """Spong's acrobot: two links, torque ``τ2`` at the elbow only; q1 = q2 = 0 hangs down.

    ``x = [q1, q2, q̇1, q̇2]`` (q1 from the downward vertical, q2 relative to link 1), ``u = [τ2]``.
    Defaults are Spong (1995) / Drake's: m1 = m2 = 1, l1 = 1, l2 = 2 (enters only through the
    centre of mass), lc1 = 0.5, lc2 = 1, inertias about the centres of mass I1 = 1/12 and
    I2 = 1/3 (uniform rods; Spong rounds them to 0.083 and 0.33), g = 9.81, no friction::

        M = [[I1 + I2 + m2 l1² + 2 m2 l1 lc2 c2,  I2 + m2 l1 lc2 c2], [I2 + m2 l1 lc2 c2,  I2]]
        C q̇ = [−m2 l1 lc2 s2 (2 q̇1 q̇2 + q̇2²),  m2 l1 lc2 s2 q̇1²]
        τ_g = [−m1 g lc1 s1 − m2 g (l1 s1 + lc2 s12),  −m2 g lc2 s12]

    with I1, I2 here about the joints (``link_inertia_i + m_i lc_i²``).
    """
    params = _params(
        link_mass_1=link_mass_1, link_mass_2=link_mass_2, link_length_1=link_length_1,
        link_com_1=link_com_1, link_com_2=link_com_2,
        link_inertia_1=link_inertia_1, link_inertia_2=link_inertia_2, gravity=gravity,
    )
    return Model("acrobot", 4, 1, _acrobot, params, ("q1", "q2", "q1dot", "q2dot"), ("tau2",))


# ------------------------------------------------------------------------------ registry
_REGISTRY: dict[str, Callable[..., Model]] = {
    "double_integrator": double_integrator,
    "pendulum": pendulum,
    "cartpole": cartpole,
    "unicycle": unicycle,
    "quadrotor2d": quadrotor2d,
    "acrobot": acrobot,
}


def names() -> list[str]:
    """Names of the registered models."""
    return list(_REGISTRY)


def get(name: str, **overrides: float) -> Model:
    """The model ``name`` with physical parameters overridden by keyword (e.g. ``mass=2.0``)."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown model {name!r}; known models are {names()}")
    return _REGISTRY[name](**overrides)
