"""Regenerate ``al_ilqr_park_starts.json`` and ``al_ilqr_quad_starts.json``: IPOPT's references for the slow tests
of AL-iLQR's (and ALTRO's) ``parallel_park`` starts 26, 35, 40 and ``quadrotor2d`` starts 6, 29
(``tests/test_altro_defaults.py``): IPOPT (CasADi, tol 1e-8) warm-started (``mu_init`` 1e-9) at AL-iLQR's solutions
from ``sample_x0(problem, 64, 0)``'s starts, and cold from the same starts. Run from the repository root:
``python tests/data/make_al_ilqr_starts.py``.
"""

import json
from pathlib import Path

import torch

import torchtraj as tt
from torchtraj.bench.reference import ReferenceSolver

HERE = Path(__file__).parent
#: output file: (problem, starts of sample_x0(problem, 64, 0))
CASES = {"al_ilqr_park_starts.json": ("parallel_park", [26, 35, 40]),
         "al_ilqr_quad_starts.json": ("quadrotor2d", [6, 29])}


def reference(problem: str, starts: list) -> dict:
    x0 = tt.problems.sample_x0(problem, 64, 0)[starts]
    sol = tt.solve(tt.problems.get(problem), x0, method="al-ilqr")
    warm, cold = [], []
    for j in range(len(starts)):
        warm.append(ReferenceSolver(problem, "ipopt").solve(
            x0=x0[j].numpy(), U0=sol.U[j].numpy(), X0=sol.X[j].numpy(), warm_start=True).cost)
        cold.append(ReferenceSolver(problem, "ipopt").solve(x0=x0[j].numpy()).cost)
    note = (f"IPOPT (tol 1e-8) warm-started (mu_init 1e-9) at AL-iLQR's solutions from {problem} "
            f"sample_x0(64, seed 0) starts {', '.join(map(str, starts))}, and from the same starts cold")
    return {"problem": problem, "starts": starts, "ipopt_warm_cost": warm, "ipopt_cold_cost": cold, "note": note}


def main():
    for name, (problem, starts) in CASES.items():
        (HERE / name).write_text(json.dumps(reference(problem, starts), indent=1))


if __name__ == "__main__":
    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(1)
    main()
