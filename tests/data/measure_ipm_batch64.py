"""How tests/data/ipm_batch64.json was made (not a test; long): for each problem of the set, a batch
``problems.sample_x0(name, 64, seed=0)`` solved by the IPM at once with its default options (float64, one thread):
the statuses, iterations and the wall time, next to IPOPT's statuses on the first 16 of those starts. The first 16
rows of that draw are ``sample_x0(name, 16, seed=0)`` (the same generator, row by row), on which IPOPT was run
instance by instance for tests/data/ipm_problem_set.json (``measure_ipm_problem_set.py``): its counts are read
from there, not recomputed.

    OMP_NUM_THREADS=1 PYTHONPATH=. python tests/data/measure_ipm_batch64.py NAME [NAME ...]

Each name's row is merged into the file as it finishes (run the names one by one under a time limit).
"""

import json
import pathlib
import sys
import time

import torch

import torchtraj as tt

DATA = pathlib.Path(__file__).parent
OUT = DATA / "ipm_batch64.json"


def measure(name: str, stored: dict) -> dict:
    x0 = tt.problems.sample_x0(name, 64, seed=0)
    assert torch.equal(x0[:16], tt.problems.sample_x0(name, 16, seed=0))
    start = time.perf_counter()
    sol = tt.solve(tt.problems.get(name), x0, method="ipm")
    seconds = time.perf_counter() - start
    ok = sol.status == tt.Status.CONVERGED
    its = sol.iterations.double()
    ipopt = stored.get(name, {})
    return dict(converged=int(ok.sum()), status=tt.Status.counts(sol.status), first16_converged=int(ok[:16].sum()),
                first16_status=tt.Status.counts(sol.status[:16]), iterations_median=float(its.median()),
                iterations_max=int(its.max()), seconds=round(seconds, 1),
                ipopt_first16_converged=ipopt.get("ipopt_batch_converged"),
                ipopt_first16_failures=ipopt.get("ipopt_batch_status"))


if __name__ == "__main__":
    torch.set_num_threads(1)
    stored = json.loads((DATA / "ipm_problem_set.json").read_text())
    for name in sys.argv[1:]:
        row = measure(name, stored)
        out = json.loads(OUT.read_text()) if OUT.exists() else {}
        out[name] = row
        OUT.write_text(json.dumps(out, indent=1))
        print(name, row, flush=True)
