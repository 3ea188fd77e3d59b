"""Regenerate ``minimum_time_reference.json``: IPOPT's and FATROP's optima (CasADi) of the minimum-time problems of
:mod:`torchtraj.bench.minimum_time_problems`, transcribed as FATROP's paper does (the total time an auxiliary state
with a free ``T_0``: :mod:`torchtraj.bench.minimum_time_reference`), plus the double integrator of
``tests/test_minimum_time.py``.

Per problem: ``ipopt`` and ``fatrop`` from the rollout guess (``duration``, ``cost``, ``iterations``,
``max_violation``); ``ipopt_warm``: IPOPT warm-started (small barrier, no push off the bounds) at the interior point's
solution of the transformed problem — the local optimum of the same NLP next to the point torchtraj reaches, for a
test to compare with should the interior point end at another local optimum than IPOPT's cold start (on both
problems it now ends at the same one). Run from the repository root:
``python tests/data/make_minimum_time_reference.py``.
"""

import json
from pathlib import Path

import torch

import torchtraj as tt
from torchtraj.bench import minimum_time_problems as mtp
from torchtraj.bench.minimum_time_reference import MinimumTimeReference

OUT = Path(__file__).with_name("minimum_time_reference.json")


def record(result) -> dict:
    return {"ok": result.ok, "duration": result.duration, "cost": result.cost, "iterations": result.iterations,
            "max_violation": result.max_violation}


def main() -> None:
    out = {}
    for name in mtp.names():
        entry = {solver: record(MinimumTimeReference(name, solver).solve()) for solver in ("ipopt", "fatrop")}
        transform = mtp.get(name)
        sol = tt.solve(transform.problem, method="ipm")
        X, U, T = transform.split(sol.X[0], sol.U[0])
        warm = MinimumTimeReference(name, "ipopt").solve((X.numpy(), U.numpy(), float(T)), warm_start=True)
        entry["ipopt_warm"] = record(warm)
        out[name] = entry
        print(name, json.dumps(entry))
    OUT.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
