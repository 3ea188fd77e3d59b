"""Regenerate ``eilqr_reference.json``: IPOPT's optima (CasADi) of the equality-constrained problems of
``tests/test_eilqr.py``.

* ``pendulum_eq``, ``cartpole_eq``, ``double_integrator_eq``: the problem set's problems without their bounds, the
  goal equality ``x_N = x_g`` kept, by :class:`torchtraj.bench.reference.ReferenceSolver` on a bound-free
  :class:`~torchtraj.problems.ProblemSpec`;
* ``double_integrator_waypoint``: ``double_integrator_eq`` with the state-only equality ``p_10 = 0.8`` at the middle
  knot (no control of stage 10 acts on it);
* ``double_integrator_free_start``: ``double_integrator_eq`` with ``x_0`` free on the line ``p_0 + v_0 = 0.3``.

The last two are written here directly in CasADi (multiple shooting, RK4 of the CasADi twin of the model), not with
torchtraj. Run from the repository root: ``python tests/data/make_eilqr_reference.py``.
"""

import dataclasses
import json
from pathlib import Path

import numpy as np

from torchtraj import problems
from torchtraj.bench import casadi_models
from torchtraj.bench.reference import ReferenceSolver

OUT = Path(__file__).with_name("eilqr_reference.json")


def bound_free(name: str) -> problems.ProblemSpec:
    s = problems.spec(name)
    inf = np.inf
    return dataclasses.replace(s, name=f"{name}_eq", u_lower=np.full(s.nu, -inf), u_upper=np.full(s.nu, inf),
                               x_lower=np.full(s.nx, -inf), x_upper=np.full(s.nx, inf))


def double_integrator(waypoint: bool, free_start: bool) -> dict:
    """IPOPT on the double integrator of the problem set, bound-free, with a middle-knot waypoint or a free start."""
    ca = casadi_models.import_casadi()
    s = problems.spec("double_integrator")
    nx, nu, N = s.nx, s.nu, s.N
    step = casadi_models.rk4_step(casadi_models.get(s.model), s.dt, casadi_models.default_params(s.model))
    X = [ca.SX.sym(f"x{k}", nx) for k in range(N + 1)]
    U = [ca.SX.sym(f"u{k}", nu) for k in range(N)]
    cost, g = 0, []
    for k in range(N):
        e = X[k] - s.goal
        cost += 0.5 * ca.bilin(ca.DM(s.Q), e, e) + 0.5 * ca.bilin(ca.DM(s.R), U[k], U[k])
        g.append(X[k + 1] - step(X[k], U[k]))
    e = X[N] - s.goal
    cost += 0.5 * ca.bilin(ca.DM(s.Qf), e, e)
    g.append(X[N] - s.goal)
    g.append(X[0][0] + X[0][1] - 0.3 if free_start else X[0] - s.x0)
    if waypoint:
        g.append(X[10][0] - 0.8)
    w = ca.vertcat(*X, *U)
    solver = ca.nlpsol("s", "ipopt", {"x": w, "f": cost, "g": ca.vertcat(*g)},
                       {"ipopt": {"tol": 1e-12, "print_level": 0, "sb": "yes"}, "print_time": False})
    sol = solver(x0=np.zeros(w.shape[0]), lbg=0, ubg=0)
    w = np.asarray(sol["x"]).ravel()
    assert solver.stats()["success"]
    return {"cost": float(sol["f"]), "X": w[: (N + 1) * nx].reshape(N + 1, nx).tolist(),
            "U": w[(N + 1) * nx:].reshape(N, nu).tolist()}


def main():
    out = {}
    for name in ("pendulum", "cartpole", "double_integrator"):
        r = ReferenceSolver(bound_free(name), "ipopt", tol=1e-10).solve()
        assert r.ok, r.status
        out[f"{name}_eq"] = {"cost": r.cost, "X": r.X.tolist(), "U": r.U.tolist(), "iterations": r.iterations}
    out["double_integrator_waypoint"] = double_integrator(waypoint=True, free_start=False)
    out["double_integrator_free_start"] = double_integrator(waypoint=False, free_start=True)
    OUT.write_text(json.dumps(out))
    for k, v in out.items():
        print(k, v["cost"])


if __name__ == "__main__":
    main()
