"""Regenerate ``al_ilqr_quad_starts.json``: IPOPT's reference for the slow test of AL-iLQR's ``quadrotor2d`` starts
6 and 29 (``tests/test_altro_defaults.py``): IPOPT (CasADi, tol 1e-8) warm-started (``mu_init`` 1e-9) at AL-iLQR's
solutions from ``sample_x0("quadrotor2d", 64, 0)``'s starts, and cold from the same starts. Run from the repository
root: ``python tests/data/make_al_ilqr_quad_starts.py``.
"""

import json
from pathlib import Path

import torch

import torchtraj as tt
from torchtraj.bench.reference import ReferenceSolver

OUT = Path(__file__).with_name("al_ilqr_quad_starts.json")
STARTS = [6, 29]


def main():
    x0 = tt.problems.sample_x0("quadrotor2d", 64, 0)[STARTS]
    sol = tt.solve(tt.problems.get("quadrotor2d"), x0, method="al-ilqr")
    warm, cold = [], []
    for j in range(len(STARTS)):
        warm.append(ReferenceSolver("quadrotor2d", "ipopt").solve(
            x0=x0[j].numpy(), U0=sol.U[j].numpy(), X0=sol.X[j].numpy(), warm_start=True).cost)
        cold.append(ReferenceSolver("quadrotor2d", "ipopt").solve(x0=x0[j].numpy()).cost)
    note = ("IPOPT (tol 1e-8) warm-started (mu_init 1e-9) at AL-iLQR's solutions from quadrotor2d "
            "sample_x0(64, seed 0) starts 6 and 29, and from the same starts cold")
    OUT.write_text(json.dumps({"problem": "quadrotor2d", "starts": STARTS, "ipopt_warm_cost": warm,
                               "ipopt_cold_cost": cold, "note": note}, indent=1))


if __name__ == "__main__":
    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(1)
    main()
