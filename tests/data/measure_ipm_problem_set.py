"""How tests/data/ipm_problem_set.json was made (not a test; long): for each problem of the set, the IPM with its
default options from the problem's own guess (B = 1) next to IPOPT's stored iterations (tests/data/reference.json),
and a batch ``problems.sample_x0(name, 16, seed=0)`` solved by the IPM at once and by IPOPT instance by instance
(``torchtraj.bench.reference.ReferenceSolver``, its defaults): the statuses, iterations and relative cost differences.

    PYTHONPATH=. python tests/data/measure_ipm_problem_set.py [NAME ...]
"""

import json
import pathlib
import sys

import torchtraj as tt
from torchtraj.bench.reference import ReferenceSolver

DATA = pathlib.Path(__file__).parent


def measure(name: str, reference: dict) -> dict:
    problem = tt.problems.get(name)
    sol = tt.solve(problem, method="ipm")
    row = dict(status=tt.Status.describe(sol.status)[0], iterations=int(sol.iterations[0]), cost=float(sol.cost[0]),
               ipopt_iterations=reference[name]["ipopt"]["iterations"], ipopt_cost=reference[name]["ipopt"]["cost"])
    try:
        x0 = tt.problems.sample_x0(name, 16, seed=0)
    except ValueError as error:  # car_escape: no spread in the problem set
        return {**row, "batch": str(error)}
    batch = tt.solve(problem, x0, method="ipm")
    ipopt = ReferenceSolver(name, "ipopt")
    refs = [ipopt.solve(x0=x0[i].numpy()) for i in range(16)]
    ok = batch.converged.tolist()
    return {**row, "batch_converged": int(batch.converged.sum()), "batch_status": tt.Status.counts(batch.status),
            "batch_iterations": batch.iterations.tolist(), "ipopt_batch_converged": sum(r.ok for r in refs),
            "ipopt_batch_status": [r.status for r in refs if not r.ok],
            "ipopt_batch_iterations": [r.iterations for r in refs],
            "batch_cost_vs_ipopt": [(float(batch.cost[i]) - r.cost) / r.cost if ok[i] and r.ok else None
                                    for i, r in enumerate(refs)]}


if __name__ == "__main__":
    reference = json.loads((DATA / "reference.json").read_text())
    out = {name: measure(name, reference) for name in (sys.argv[1:] or tt.problems.names())}
    (DATA / "ipm_problem_set.json").write_text(json.dumps(out, indent=1))
