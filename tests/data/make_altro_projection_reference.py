"""Regenerate ``altro_projection_reference.json``: the input and the reference of ALTRO's projection test on the 2-D
quadrotor (``tests/test_altro_defaults.py``).

The input is the point where ALTRO's augmented-Lagrangian stage ends on ``quadrotor2d`` with default options from the
problem's own guesses (its states, controls, multipliers and penalties, as the projection receives them). The
reference is IPOPT (CasADi, :mod:`torchtraj.bench.reference`) warm-started at that point: the local optimum it keeps
there (cost, states, controls), the one the projection must reach. It is another local optimum than IPOPT's from a
cold start (``tests/data/reference.json``), 0.19 relative below it. Run from the repository root:
``python tests/data/make_altro_projection_reference.py``.
"""

import json
from pathlib import Path

import torch

import torchtraj as tt
from torchtraj.bench.reference import ReferenceSolver
from torchtraj.core.batch import Batch
from torchtraj.core.batching import rollout
from torchtraj.solvers.altro.options import ALTROOptions
from torchtraj.solvers.altro.stages import al_stage

OUT = Path(__file__).with_name("altro_projection_reference.json")
NAME = "quadrotor2d"


def main():
    torch.set_default_dtype(torch.float64)
    problem = tt.problems.get(NAME)
    batch = Batch.build(problem).for_solver()
    X = rollout(problem.dynamics, batch.x0, batch.U0, batch.params)
    stage = al_stage(problem, batch.x0, X, batch.U0, batch.params, ALTROOptions(), "altro")
    assert bool(stage.al_done[0]), "the AL stage did not finish"
    d = stage.al.duals
    ipopt = ReferenceSolver(NAME, "ipopt").solve(U0=stage.U[0].numpy(), X0=stage.X[0].numpy(), warm_start=True)
    assert ipopt.ok, ipopt.status
    data = {
        "problem": NAME,
        "al_stage": {"X": stage.X[0].tolist(), "U": stage.U[0].tolist(), "stage": d.stage[0].tolist(),
                     "terminal": d.terminal[0].tolist(), "stage_penalty": d.stage_penalty[0].tolist(),
                     "terminal_penalty": d.terminal_penalty[0].tolist()},
        "ipopt_warm": {"cost": ipopt.cost, "max_violation": ipopt.max_violation, "X": ipopt.X.tolist(),
                       "U": ipopt.U.tolist()},
    }
    OUT.write_text(json.dumps(data))
    print(f"wrote {OUT}: IPOPT warm-started at the AL stage's end, cost {ipopt.cost:.10g}")


if __name__ == "__main__":
    main()
