"""IPOPT's optima (``torchtraj.bench.reference.ReferenceSolver``, its defaults) from the starts of
``problems.sample_x0("quadrotor2d", 64, seed=0)`` on which eILQR or HM-iLQR stopped short with default options
(issue 23; ``tests/test_eilqr_quadrotor.py``), written to ``quadrotor2d_starts.json`` as
``{start: {"cost", "ok", "iterations", "max_violation"}}``. Not a test.

    PYTHONPATH=. python tests/data/make_quadrotor2d_starts.py START [START ...]
"""

import json
import pathlib
import sys

import torchtraj as tt
from torchtraj.bench.reference import ReferenceSolver

OUT = pathlib.Path(__file__).parent / "quadrotor2d_starts.json"

if __name__ == "__main__":
    x0 = tt.problems.sample_x0("quadrotor2d", 64, seed=0)
    ipopt = ReferenceSolver("quadrotor2d", "ipopt")
    out = json.loads(OUT.read_text()) if OUT.exists() else {}
    for start in map(int, sys.argv[1:]):
        r = ipopt.solve(x0=x0[start].numpy())
        out[str(start)] = {"cost": r.cost, "ok": r.ok, "iterations": r.iterations,
                           "max_violation": r.max_violation}
        print(start, out[str(start)], flush=True)
    OUT.write_text(json.dumps(dict(sorted(out.items(), key=lambda kv: int(kv[0]))), indent=1))
