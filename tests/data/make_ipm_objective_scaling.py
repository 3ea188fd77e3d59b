"""How tests/data/ipm_objective_scaling.json was made (not a test): IPOPT (CasADi, tol 1e-8, its defaults, among
them ``nlp_scaling_method = gradient-based``) on cartpole_unconstrained from start 59 of
``problems.sample_x0("cartpole_unconstrained", 64, seed=0)`` and the problem set's guess (the rollout of
``u_init``), through torchtraj.bench.reference: its status, iterations, optimum (cost, controls), objective at
each iterate, and its objective scaling factor ``s_f``, read from its printed summary (the objective scaled and
unscaled at the solution; their ratio).

    PYTHONPATH=. python tests/data/make_ipm_objective_scaling.py
"""

import json
import os
import pathlib
import re
import tempfile

import torchtraj as tt
from torchtraj.bench.reference import ReferenceSolver

START = 59


class Printing(ReferenceSolver):
    def _ipopt_options(self, **changes):
        options = super()._ipopt_options(**changes)
        options["ipopt"]["print_level"] = 5
        return options


def printed(call):
    """``call()``'s result and what IPOPT printed meanwhile (its C-level stdout)."""
    with tempfile.TemporaryFile(mode="w+") as capture:
        saved = os.dup(1)
        os.dup2(capture.fileno(), 1)
        try:
            result = call()
        finally:
            os.dup2(saved, 1)
            os.close(saved)
        capture.seek(0)
        return result, capture.read()


x0 = tt.problems.sample_x0("cartpole_unconstrained", 64, seed=0)[START].numpy()
solver = Printing("cartpole_unconstrained")
result, text = printed(lambda: solver.solve(x0))
scaled, unscaled = (float(v) for v in re.search(r"Objective\.+:\s+(\S+)\s+(\S+)", text).groups())
stats = solver._solver.stats()
out = {"_about": "IPOPT on cartpole_unconstrained from sample_x0(name, 64, seed=0)[59] and the rollout of u_init; "
                 "made by tests/data/make_ipm_objective_scaling.py",
       "start": START, "status": result.status, "iterations": result.iterations, "cost": result.cost,
       "objective_scale": scaled / unscaled, "objective": [float(v) for v in stats["iterations"]["obj"]],
       "U": result.U.ravel().tolist()}
(pathlib.Path(__file__).parent / "ipm_objective_scaling.json").write_text(json.dumps(out, indent=1) + "\n")
print({k: v for k, v in out.items() if k not in ("U", "objective")})
