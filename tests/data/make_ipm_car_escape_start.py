"""How tests/data/ipm_car_escape_start.json was made (not a test): IPOPT's start on car_escape, the problem set's
own guess (its waypoint states ``X_init`` and ``u_init``, ``ReferenceSolver.initial_guess``), evaluated by CasADi:
the objective and the largest violation of the NLP's rows there; and IPOPT from the rollout of ``u_init`` instead
of the waypoints (the start the IPM took when it ignored ``X_init``): its status and iterations.

    PYTHONPATH=. python tests/data/make_ipm_car_escape_start.py
"""

import json
import pathlib

import casadi as ca
import numpy as np

from torchtraj.bench.reference import ReferenceSolver

reference = ReferenceSolver("car_escape", "ipopt")
spec = reference.spec
X0, U0 = reference.initial_guess(spec.x0)
w0 = np.concatenate([np.hstack([X0[:-1], U0]).ravel(), X0[-1]])
nlp = reference._nlp
f = ca.Function("f", [nlp["x"], nlp["p"]], [nlp["f"]])
g = np.asarray(reference._g(w0, spec.x0)).ravel()
violation = np.maximum(np.maximum(reference._lbg - g, g - reference._ubg), 0.0).max()
rollout = np.vstack([spec.x0, np.asarray(reference._step.mapaccum(spec.N)(spec.x0, U0.T)).T])
from_rollout = reference.solve(X0=rollout)
out = {
    "_about": "IPOPT's start on car_escape (the problem set's waypoint states X_init and u_init): objective and "
              "largest row violation there (CasADi); IPOPT (its defaults, tol 1e-8) from the rollout of u_init "
              "instead. Made by tests/data/make_ipm_car_escape_start.py.",
    "start_cost": float(f(w0, spec.x0)),
    "start_violation": float(violation),
    "ipopt_from_rollout": {"status": from_rollout.status, "iterations": from_rollout.iterations},
}
(pathlib.Path(__file__).parent / "ipm_car_escape_start.json").write_text(json.dumps(out, indent=1) + "\n")
print(out)
