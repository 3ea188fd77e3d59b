"""IPOPT's optima (``torchtraj.bench.reference.ReferenceSolver``, its defaults) from the 64 starts of
``problems.sample_x0(name, 64, seed=0)`` of the cart-pole and its bound-free twin, on which eILQR's monotone line
search crawled to ``MAX_ITERATIONS`` (issue 23; ``tests/test_eilqr.py``), written to ``eilqr_batch64.json``:
per problem the lists ``cost``, ``ok`` and ``iterations``, indexed by start. Not a test.

    PYTHONPATH=. python tests/data/make_eilqr_batch64.py
"""

import json
import pathlib

import torchtraj as tt
from torchtraj.bench.reference import ReferenceSolver

OUT = pathlib.Path(__file__).parent / "eilqr_batch64.json"
PROBLEMS = ("cartpole", "cartpole_unconstrained")

if __name__ == "__main__":
    out = {}
    for name in PROBLEMS:
        x0 = tt.problems.sample_x0(name, 64, seed=0)
        ipopt = ReferenceSolver(name, "ipopt")
        refs = [ipopt.solve(x0=x0[i].numpy()) for i in range(64)]
        out[name] = {"cost": [r.cost for r in refs], "ok": [r.ok for r in refs],
                     "iterations": [r.iterations for r in refs]}
        print(name, sum(r.ok for r in refs), "of 64 solved")
    OUT.write_text(json.dumps(out, indent=1))
