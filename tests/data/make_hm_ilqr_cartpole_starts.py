"""IPOPT's optima (``torchtraj.bench.reference.ReferenceSolver``, its defaults) from the ``cartpole_unconstrained``
starts of ``problems.sample_x0("cartpole_unconstrained", 64, seed=0)`` on which HM-iLQR's default options ended
``MAX_ITERATIONS`` (0, 8, 10) or ``STALLED`` (1, 4, 7) before the dynamics' curvature and the second-order
correction (``tests/test_hm_ilqr.py``), written to ``hm_ilqr_cartpole_starts.json``. Not a test.

    PYTHONPATH=. python tests/data/make_hm_ilqr_cartpole_starts.py
"""

import json
import pathlib

import torchtraj as tt
from torchtraj.bench.reference import ReferenceSolver

OUT = pathlib.Path(__file__).parent / "hm_ilqr_cartpole_starts.json"
NAME = "cartpole_unconstrained"
STARTS = (0, 1, 4, 7, 8, 10)

if __name__ == "__main__":
    x0 = tt.problems.sample_x0(NAME, 64, seed=0)
    ipopt = ReferenceSolver(NAME, "ipopt")
    out = {}
    for i in STARTS:
        ref = ipopt.solve(x0=x0[i].numpy())
        assert ref.ok, ref.status
        out[str(i)] = {"cost": ref.cost, "iterations": ref.iterations, "status": ref.status}
    OUT.write_text(json.dumps(out, indent=1) + "\n")
    print(out)
