"""IPOPT's optima (``torchtraj.bench.reference.ReferenceSolver``, its defaults, cold) from starts of
``problems.sample_x0(problem, 64, seed=0)`` on which a method's default options once stopped short (issue 23), as
``{start: {"cost", "ok", "status", "iterations", "max_violation"}}``. The tests read the costs:

- ``eilqr_cartpole_starts.json``: ``cartpole`` 3, 6, where eILQR crawled to ``MAX_ITERATIONS`` before the step was
  truncated to the barrier's domain (``tests/test_eilqr.py``);
- ``hm_ilqr_cartpole_starts.json``: ``cartpole_unconstrained`` 0, 1, 4, 7, 8, 10, where HM-iLQR ended
  ``MAX_ITERATIONS`` or ``STALLED`` before the dynamics' curvature and the second-order correction
  (``tests/test_hm_ilqr.py``);
- ``hm_ilqr_cartpole_bounded_starts.json``: ``cartpole`` 18, 19, 36, where HM-iLQR ended ``MAX_ITERATIONS`` before the
  shifted curvature and the defect weight's floor of ``μ_V^0`` steps (``tests/test_hm_ilqr.py``);
- ``quadrotor2d_starts.json``: ``quadrotor2d`` 17, 38, 47, 50, 53, where eILQR or HM-iLQR stopped short
  (``tests/test_eilqr_quadrotor.py``, ``tests/test_hm_ilqr_quadrotor.py``).

Not a test. Run from the repository root: ``PYTHONPATH=. python tests/data/make_ipopt_starts.py``.
"""

import json
import pathlib

import torchtraj as tt
from torchtraj.bench.reference import ReferenceSolver

HERE = pathlib.Path(__file__).parent
#: output file: (problem, starts of sample_x0(problem, 64, seed=0))
CASES = {"eilqr_cartpole_starts.json": ("cartpole", (3, 6)),
         "hm_ilqr_cartpole_starts.json": ("cartpole_unconstrained", (0, 1, 4, 7, 8, 10)),
         "hm_ilqr_cartpole_bounded_starts.json": ("cartpole", (18, 19, 36)),
         "quadrotor2d_starts.json": ("quadrotor2d", (17, 38, 47, 50, 53))}


def reference(problem: str, starts: tuple) -> dict:
    x0 = tt.problems.sample_x0(problem, 64, seed=0)
    ipopt = ReferenceSolver(problem, "ipopt")
    out = {}
    for start in starts:
        r = ipopt.solve(x0=x0[start].numpy())
        assert r.ok, (problem, start, r.status)
        out[str(start)] = {"cost": r.cost, "ok": r.ok, "status": r.status, "iterations": r.iterations,
                           "max_violation": r.max_violation}
        print(problem, start, out[str(start)], flush=True)
    return out


if __name__ == "__main__":
    for name, (problem, starts) in CASES.items():
        (HERE / name).write_text(json.dumps(reference(problem, starts), indent=1) + "\n")
