"""The continuous models of :mod:`torchtraj.models` written again in CasADi symbols.

Each function ``f(x, u, p) -> xdot`` takes CasADi column vectors (SX or MX) ``x (nx, 1)``,
``u (nu, 1)`` and the same parameter dict as the torch model, with plain floats. The equations
are transcribed independently from the problem set (cart-pole, acrobot: by solving the 2×2 mass
matrix with ``casadi.solve`` instead of the closed form), so agreement with the torch models
is a real check. CasADi is imported lazily: see :func:`import_casadi`.
"""

from __future__ import annotations

from typing import Callable, Mapping

import numpy as np

from .. import models

CasadiDynamics = Callable[..., object]


def import_casadi():
    """The ``casadi`` module, or an ImportError that says how to install it."""
    try:
        import casadi
    except ImportError as exc:  # optional dependency
        raise ImportError(
            "torchtraj.bench needs CasADi for its IPOPT / FATROP references: pip install torchtraj[bench]"
        ) from exc
    return casadi


def double_integrator(x, u, p: Mapping[str, float]):
    ca = import_casadi()
    return ca.vertcat(x[1], u[0])


def pendulum(x, u, p: Mapping[str, float]):
    ca = import_casadi()
    m, l, b, g = p["mass"], p["length"], p["damping"], p["gravity"]
    return ca.vertcat(x[1], (u[0] - m * g * l * ca.sin(x[0]) - b * x[1]) / (m * l**2))


def cartpole(x, u, p: Mapping[str, float]):
    ca = import_casadi()
    mc, mp, l, g = p["cart_mass"], p["pole_mass"], p["pole_length"], p["gravity"]
    theta, qdot = x[1], x[2:4]
    s, c = ca.sin(theta), ca.cos(theta)
    H = ca.vertcat(ca.horzcat(mc + mp, mp * l * c), ca.horzcat(mp * l * c, mp * l**2))
    C = ca.vertcat(ca.horzcat(0, -mp * x[3] * l * s), ca.horzcat(0, 0))
    G = ca.vertcat(0, mp * g * l * s)
    B = ca.vertcat(1, 0)
    qddot = ca.solve(H, -(C @ qdot + G - B * u[0]))
    return ca.vertcat(qdot, qddot)


def unicycle(x, u, p: Mapping[str, float]):
    ca = import_casadi()
    return ca.vertcat(u[0] * ca.cos(x[2]), u[0] * ca.sin(x[2]), u[1])


def quadrotor2d(x, u, p: Mapping[str, float]):
    ca = import_casadi()
    m, arm, g = p["mass"], p["arm_length"], p["gravity"]
    J = 0.2 * m * arm**2
    thrust = u[0] + u[1]
    return ca.vertcat(
        x[3:6],
        thrust * ca.sin(x[2]) / m,
        thrust * ca.cos(x[2]) / m - g,
        (arm / 2) * (u[1] - u[0]) / J,
    )


def acrobot(x, u, p: Mapping[str, float]):
    ca = import_casadi()
    m1, m2, l1 = p["link_mass_1"], p["link_mass_2"], p["link_length_1"]
    lc1, lc2, g = p["link_com_1"], p["link_com_2"], p["gravity"]
    I1 = p["link_inertia_1"] + m1 * lc1**2
    I2 = p["link_inertia_2"] + m2 * lc2**2
    q1, q2, dq1, dq2 = x[0], x[1], x[2], x[3]
    s1, s2, c2, s12 = ca.sin(q1), ca.sin(q2), ca.cos(q2), ca.sin(q1 + q2)
    M = ca.vertcat(
        ca.horzcat(I1 + I2 + m2 * l1**2 + 2 * m2 * l1 * lc2 * c2, I2 + m2 * l1 * lc2 * c2),
        ca.horzcat(I2 + m2 * l1 * lc2 * c2, I2),
    )
    C = ca.vertcat(
        ca.horzcat(-2 * m2 * l1 * lc2 * s2 * dq2, -m2 * l1 * lc2 * s2 * dq2),
        ca.horzcat(m2 * l1 * lc2 * s2 * dq1, 0),
    )
    tau_g = ca.vertcat(-m1 * g * lc1 * s1 - m2 * g * (l1 * s1 + lc2 * s12), -m2 * g * lc2 * s12)
    B = ca.vertcat(0, 1)
    qddot = ca.solve(M, tau_g + B * u[0] - C @ x[2:4])
    return ca.vertcat(dq1, dq2, qddot)


_REGISTRY: dict[str, CasadiDynamics] = {
    "double_integrator": double_integrator,
    "pendulum": pendulum,
    "cartpole": cartpole,
    "unicycle": unicycle,
    "quadrotor2d": quadrotor2d,
    "acrobot": acrobot,
}


def get(name: str) -> CasadiDynamics:
    """The CasADi twin of model ``name`` in :mod:`torchtraj.models`."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown model {name!r}; known models are {sorted(_REGISTRY)}")
    return _REGISTRY[name]


def default_params(name: str) -> dict[str, float]:
    """The torch model's default physical parameters as floats."""
    return {k: float(v) for k, v in models.get(name).params.items()}


def rk4_step(f: CasadiDynamics, dt: float, p: Mapping[str, float]):
    """A CasADi-symbolic classic RK4 step ``(x, u) -> x_next`` of ``f`` (control held constant)."""

    def step(x, u):
        k1 = f(x, u, p)
        k2 = f(x + dt / 2 * k1, u, p)
        k3 = f(x + dt / 2 * k2, u, p)
        k4 = f(x + dt * k3, u, p)
        return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

    return step


def evaluate(name: str, x: np.ndarray, u: np.ndarray, params: Mapping[str, float] | None = None) -> np.ndarray:
    """Numeric ``xdot`` of the CasADi twin at one point, ``x (nx,)``, ``u (nu,)`` -> ``(nx,)``."""
    ca = import_casadi()
    p = default_params(name) if params is None else dict(params)
    return np.asarray(ca.DM(get(name)(ca.DM(x), ca.DM(u), p))).ravel()
