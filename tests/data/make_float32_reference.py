"""Regenerate ``float32_reference.json``: IPOPT's optima (CasADi) of the constrained double integrator of
``tests/test_float32_barrier_methods.py`` and the gradients of the optimal cost with respect to ``x_0``.

The problem, written here directly in CasADi (multiple shooting): ``p' = v``, ``v' = u``, RK4 with ``dt = 0.1``,
``N = 40``; cost ``Σ_{k<N} 0.1 u_k² + |x_k − g|² + 10 |x_N − g|²`` with ``g = (1, 0)``; ``|u_k| ≤ 1`` and
``v_k ≤ 0.5`` on the knots ``1..N−1``. The starts are eight of ``0.5 · randn`` of seed 0 with ``v`` clipped to
``[−0.35, 0.35]`` (a start at ``v = ±0.4`` reaches ``v = 0.5`` on the grid at full thrust, ``v_k = v_0 + 0.1 k``,
where the rows ``v_k ≤ 0.5`` and ``u ≤ 1`` are active together and dependent: no derivative exists there). The gradient
is the central difference of two IPOPT optima ``h = 1e-4`` apart in each component (IPOPT's ``tol = 1e-12``). Run from
the repository root: ``python tests/data/make_float32_reference.py``.
"""

import json
from pathlib import Path

import numpy as np
import torch

from torchtraj.bench.casadi_models import double_integrator, rk4_step

OUT = Path(__file__).with_name("float32_reference.json")
N, DT, B, H = 40, 0.1, 8, 1e-4


def starts() -> np.ndarray:
    x0 = 0.5 * torch.randn(32, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    x0[:, 1] = x0[:, 1].clamp(-0.35, 0.35)
    return x0[:B].numpy()


def solver():
    import casadi as ca
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    F = ca.Function("F", [x, u], [rk4_step(double_integrator, DT, {})(x, u)])
    opti = ca.Opti()
    X, U, p = opti.variable(2, N + 1), opti.variable(1, N), opti.parameter(2)
    goal = ca.DM([1.0, 0.0])
    cost = 0
    for k in range(N):
        cost += 0.1 * U[0, k] ** 2 + ca.sumsqr(X[:, k] - goal)
        opti.subject_to(X[:, k + 1] == F(X[:, k], U[:, k]))
        opti.subject_to(opti.bounded(-1.0, U[0, k], 1.0))
        if k >= 1:
            opti.subject_to(X[1, k] <= 0.5)
    cost += 10 * ca.sumsqr(X[:, N] - goal)
    opti.subject_to(X[:, 0] == p)
    opti.minimize(cost)
    opti.solver("ipopt", {"print_time": False}, {"tol": 1e-12, "print_level": 0})

    def solve(x0):
        opti.set_value(p, x0)
        sol = opti.solve()
        return float(sol.value(cost)), np.array(sol.value(U)).reshape(N, 1)

    return solve


def main():
    solve = solver()
    rows = []
    for x0 in starts():
        cost, U = solve(x0)
        grad = []
        for i in range(2):
            e = np.zeros(2)
            e[i] = H
            grad.append((solve(x0 + e)[0] - solve(x0 - e)[0]) / (2 * H))
        rows.append({"x0": x0.tolist(), "cost": cost, "U": U.tolist(), "grad_x0": grad})
    OUT.write_text(json.dumps({"double_integrator_v_bound": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
