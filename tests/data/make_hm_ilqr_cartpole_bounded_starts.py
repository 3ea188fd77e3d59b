"""IPOPT's optima (``torchtraj.bench.reference.ReferenceSolver``, its defaults) from the ``cartpole`` starts of
``problems.sample_x0("cartpole", 64, seed=0)`` on which HM-iLQR's default options ended ``MAX_ITERATIONS`` (or
``MAX_REGULARIZATION``) before the shifted curvature and the defect weight's floor of ``μ_V^0`` steps (18, 19, 36;
issue 23, ``tests/test_hm_ilqr.py``), written to ``hm_ilqr_cartpole_bounded_starts.json`` as
``{start: {"cost", "ok", "iterations", "max_violation"}}``. Not a test.

    PYTHONPATH=. python tests/data/make_hm_ilqr_cartpole_bounded_starts.py
"""

import json
import pathlib

import torchtraj as tt
from torchtraj.bench.reference import ReferenceSolver

OUT = pathlib.Path(__file__).parent / "hm_ilqr_cartpole_bounded_starts.json"
STARTS = (18, 19, 36)

if __name__ == "__main__":
    x0 = tt.problems.sample_x0("cartpole", 64, seed=0)
    ipopt = ReferenceSolver("cartpole", "ipopt")
    out = {}
    for start in STARTS:
        r = ipopt.solve(x0=x0[start].numpy())
        assert r.ok, r.status
        out[str(start)] = {"cost": r.cost, "ok": r.ok, "iterations": r.iterations, "max_violation": r.max_violation}
        print(start, out[str(start)], flush=True)
    OUT.write_text(json.dumps(out, indent=1) + "\n")
