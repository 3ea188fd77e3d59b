"""Regenerate ``altro_polish_park.json``: the input and the reference of the projection-polish test on
``parallel_park`` (``tests/test_altro_defaults.py``).

The input is where ALTRO's augmented-Lagrangian stage ends from ``sample_x0("parallel_park", 64, 0)``'s starts 26
and 40 (states, controls, multipliers and penalties, as the projection receives them), with the multiplier-sign test
off (``multiplier_signs=False``: the AL stage as it was when the polish's short count was found; with the test on it
ends elsewhere). The reference is IPOPT (CasADi, :mod:`torchtraj.bench.reference`) warm-started at the solutions
ALTRO reaches from there, and cold from the same starts. Run from the repository root:
``python tests/data/make_altro_polish_park.py``.
"""

import json
from pathlib import Path

import torch

import torchtraj as tt
from torchtraj.bench.reference import ReferenceSolver
from torchtraj.solvers.altro import stages

OUT = Path(__file__).with_name("altro_polish_park.json")
STARTS = [26, 40]


def main():
    captured = {}
    project = stages.project

    def capture(al, params, x0, X, U, mask, opts):
        captured.update(al=al, X=X.clone(), U=U.clone(), mask=mask.clone())
        return project(al, params, x0, X, U, mask, opts)

    stages.project = capture
    x0 = tt.problems.sample_x0("parallel_park", 64, 0)[STARTS]
    sol = tt.solve(tt.problems.get("parallel_park"), x0, method="altro",
                   options=tt.ALTROOptions(multiplier_signs=False))
    stages.project = project
    d = captured["al"].duals
    out = {"problem": "parallel_park", "starts": STARTS, "x0": x0.tolist(), "mask": captured["mask"].tolist(),
           "al_stage": {"X": captured["X"].tolist(), "U": captured["U"].tolist(), "stage": d.stage.tolist(),
                        "terminal": d.terminal.tolist(), "stage_penalty": d.stage_penalty.tolist(),
                        "terminal_penalty": d.terminal_penalty.tolist()}, "ipopt_warm": []}
    for j in range(len(STARTS)):
        warm = ReferenceSolver("parallel_park", "ipopt").solve(x0=x0[j].numpy(), U0=sol.U[j].numpy(),
                                                               X0=sol.X[j].numpy(), warm_start=True)
        cold = ReferenceSolver("parallel_park", "ipopt").solve(x0=x0[j].numpy())
        out["ipopt_warm"].append({"cost": warm.cost, "max_violation": warm.max_violation, "cold_cost": cold.cost})
    OUT.write_text(json.dumps(out))


if __name__ == "__main__":
    torch.set_default_dtype(torch.float64)
    main()
