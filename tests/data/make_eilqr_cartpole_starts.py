"""IPOPT's optima (``torchtraj.bench.reference.ReferenceSolver``, its defaults) from the cart-pole starts 3 and 6 of
``problems.sample_x0("cartpole", 64, seed=0)``, on which eILQR's default options crawled to ``MAX_ITERATIONS``
before the step was truncated to the barrier's domain (``tests/test_eilqr.py``), written to
``eilqr_cartpole_starts.json``. Not a test.

    PYTHONPATH=. python tests/data/make_eilqr_cartpole_starts.py
"""

import json
import pathlib

import torchtraj as tt
from torchtraj.bench.reference import ReferenceSolver

OUT = pathlib.Path(__file__).parent / "eilqr_cartpole_starts.json"
STARTS = (3, 6)

if __name__ == "__main__":
    x0 = tt.problems.sample_x0("cartpole", 64, seed=0)
    ipopt = ReferenceSolver("cartpole", "ipopt")
    out = {}
    for i in STARTS:
        ref = ipopt.solve(x0=x0[i].numpy())
        assert ref.ok, ref.status
        out[str(i)] = {"cost": ref.cost, "iterations": ref.iterations, "status": ref.status}
    OUT.write_text(json.dumps(out, indent=1))
    print(out)
