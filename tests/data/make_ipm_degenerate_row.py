"""How tests/data/ipm_degenerate_row.json was made (not a test): IPOPT (CasADi, tol 1e-8, its defaults) on the
double integrator of tests/test_ipm_safeguards.py (RK4, dt 0.1, N = 20, |u| ≤ 1, from (0.3, 0.1), the rollout of
u = 0 as the guess; the bounds as two-sided rows, as the problem set's references pose them) with the terminal row
``(x_N,0 − 1)² = 0``, whose gradient vanishes where it holds: its status, iterations and objective at each iterate.

    PYTHONPATH=. python tests/data/make_ipm_degenerate_row.py
"""

import json
import pathlib

import casadi as ca
import numpy as np

N, dt = 20, 0.1
x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)


def f(x, u):
    return ca.vertcat(x[1], u[0])


k1 = f(x, u)
k2 = f(x + dt / 2 * k1, u)
k3 = f(x + dt / 2 * k2, u)
k4 = f(x + dt * k3, u)
step = ca.Function("F", [x, u], [x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])
X = [ca.SX.sym(f"x{k}", 2) for k in range(N + 1)]
U = [ca.SX.sym(f"u{k}", 1) for k in range(N)]
goal, x0 = np.array([1.0, 0.0]), np.array([0.3, 0.1])
cost, rows = 0, []
for k in range(N):
    cost += 0.1 * ca.sumsqr(U[k]) + ca.sumsqr(X[k] - goal)
    rows.append(X[k + 1] - step(X[k], U[k]))
cost += 10 * ca.sumsqr(X[N] - goal)
rows += [X[0] - x0, (X[N][0] - 1) ** 2]
bounds = U  # |u| <= 1 as two-sided rows, as the problem set's references pose bounds (torchtraj.bench.reference)
solver = ca.nlpsol("degenerate", "ipopt", {"x": ca.vertcat(*X, *U), "f": cost, "g": ca.vertcat(*rows, *bounds)},
                   {"ipopt": {"tol": 1e-8, "print_level": 0, "sb": "yes"}, "print_time": False})
guess = [x0]
for k in range(N):
    guess.append(np.asarray(step(guess[-1], 0.0)).ravel())
result = solver(x0=np.concatenate([np.concatenate(guess), np.zeros(N)]),
                lbg=[0.0] * (2 * N + 3) + [-1.0] * N, ubg=[0.0] * (2 * N + 3) + [1.0] * N)
stats = solver.stats()
out = {"_about": "IPOPT on the double integrator with the degenerate terminal row (x_N0 - 1)^2 = 0; made by "
                 "tests/data/make_ipm_degenerate_row.py",
       "status": stats["return_status"], "iterations": stats["iter_count"],
       "objective": [float(v) for v in stats["iterations"]["obj"]],
       "violation": [float(v) for v in stats["iterations"]["inf_pr"]]}
(pathlib.Path(__file__).parent / "ipm_degenerate_row.json").write_text(json.dumps(out, indent=1) + "\n")
print(out["status"], out["iterations"], out["objective"][-3:])
