"""Regenerate ``float32_di_reference.json``: IPOPT's optima (CasADi) of the constrained double integrator of
``tests/test_altro_float32.py`` and the gradients of the optimal cost with respect to the initial state.

The problem, written here directly in CasADi (multiple shooting, not torchtraj): ``ẋ = (v, u)``, RK4 with
``dt = 0.1``, ``N = 40``, cost ``Σ_{k<N} 0.1 u_k² + |x_k − g|² + 10 |x_N − g|²`` with ``g = (1, 0)``, ``|u_k| ≤ 1``
and ``v_k ≤ 0.5`` on knots ``1..N−1``. The 32 initial states are ``0.5 · randn`` of ``torch.Generator`` seed 0 with
the speed clamped to ``[−0.4, 0.4]`` (float64), stored as used. The gradient ``dJ*/dx0`` is IPOPT's multiplier of
the initial condition ``x_0 = p`` (``lam_p``, negated), with the one-sided derivatives of the optimal cost
(``forward``, ``backward``: second-order one-sided differences, step 1e-5), which differ on the instances whose
optimum has a weakly active bound; IPOPT's gradient is one of them. Run from the repository root:
``python tests/data/make_float32_di_reference.py``.
"""

import json
from pathlib import Path

import numpy as np
import torch

from torchtraj.bench.casadi_models import double_integrator, import_casadi, rk4_step

OUT = Path(__file__).with_name("float32_di_reference.json")
N, DT, GOAL = 40, 0.1, np.array([1.0, 0.0])


def x0_batch(count: int = 32) -> np.ndarray:
    x0 = 0.5 * torch.randn(count, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    x0[:, 1] = x0[:, 1].clamp(-0.4, 0.4)
    return x0.numpy()


def build():
    ca = import_casadi()
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    step = ca.Function("step", [x, u], [rk4_step(double_integrator, DT, {})(x, u)])
    X = [ca.SX.sym(f"x{k}", 2) for k in range(N + 1)]
    U = [ca.SX.sym(f"u{k}", 1) for k in range(N)]
    p = ca.SX.sym("p", 2)
    cost, g, lbg, ubg = 0, [X[0] - p], [0, 0], [0, 0]
    for k in range(N):
        e = X[k] - GOAL
        cost += 0.1 * U[k][0] ** 2 + ca.dot(e, e)
        g.append(X[k + 1] - step(X[k], U[k]))
        lbg += [0, 0]
        ubg += [0, 0]
        g.append(U[k])
        lbg.append(-1.0)
        ubg.append(1.0)
        if k >= 1:
            g.append(X[k][1])
            lbg.append(-np.inf)
            ubg.append(0.5)
    e = X[N] - GOAL
    cost += 10 * ca.dot(e, e)
    w = ca.vertcat(*[v for k in range(N) for v in (X[k], U[k])], X[N])
    nlp = {"x": w, "f": cost, "g": ca.vertcat(*g), "p": p}
    solver = ca.nlpsol("s", "ipopt", nlp, {"print_time": False, "ipopt": {"print_level": 0, "tol": 1e-12}})
    return solver, np.array(lbg), np.array(ubg), w.shape[0]


def main():
    solver, lbg, ubg, n = build()

    def solve(x0):
        r = solver(x0=np.zeros(n), p=x0, lbg=lbg, ubg=ubg)
        assert solver.stats()["success"], solver.stats()["return_status"]
        return float(r["f"]), -np.array(r["lam_p"]).ravel()

    rows = []
    h = 1e-5
    for x0 in x0_batch():
        cost, grad = solve(x0)
        # one-sided derivatives, second order: the clamped speeds put some instances on a kink of J*(x0) (v_0 = 0.4
        # with u_0 on its bound reaches v_1 = 0.5 exactly, a weakly active bound), where the two sides differ
        sides = [np.array([(-3 * cost + 4 * solve(x0 + s * h * e)[0] - solve(x0 + 2 * s * h * e)[0]) / (2 * s * h)
                           for e in np.eye(2)]) for s in (1, -1)]
        assert all(min(abs(g - side[i]) for side in sides) <= 1e-5 * max(1.0, abs(g)) for i, g in enumerate(grad))
        rows.append({"x0": x0.tolist(), "cost": cost, "gradient": grad.tolist(), "forward": sides[0].tolist(),
                     "backward": sides[1].tolist()})
    OUT.write_text(json.dumps({"solver": "ipopt tol 1e-12", "instances": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
