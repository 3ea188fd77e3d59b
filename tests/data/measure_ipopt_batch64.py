"""IPOPT (``torchtraj.bench.reference.ReferenceSolver``, its defaults) on all 64 starts
``problems.sample_x0(name, 64, seed=0)`` of the named problems, instance by instance: which of them it solves,
written to tests/data/ipopt_batch64.json as ``ipopt_converged`` and ``ipopt_failures`` (status: count), next to
the IPM's batch in tests/data/ipm_batch64.json (``measure_ipm_batch64.py``). Not a test.

    PYTHONPATH=. python tests/data/measure_ipopt_batch64.py NAME [NAME ...]
"""

import collections
import json
import pathlib
import sys

import torchtraj as tt
from torchtraj.bench.reference import ReferenceSolver

OUT = pathlib.Path(__file__).parent / "ipopt_batch64.json"

if __name__ == "__main__":
    for name in sys.argv[1:]:
        x0 = tt.problems.sample_x0(name, 64, seed=0)
        ipopt = ReferenceSolver(name, "ipopt")
        refs = [ipopt.solve(x0=x0[i].numpy()) for i in range(64)]
        out = json.loads(OUT.read_text()) if OUT.exists() else {}
        out.setdefault(name, {}).update(ipopt_converged=sum(r.ok for r in refs), ipopt_failures=dict(
            collections.Counter(r.status for r in refs if not r.ok)))
        OUT.write_text(json.dumps(out, indent=1))
        print(name, out[name], flush=True)
