#!/bin/bash
# The GPU check of issue 19, one run (docs/benchmarks.md, "CUDA launches an iteration"): the IPM on the pendulum at
# B = 1024 and 65,536, eager and from CUDA graphs, with the launches an iteration; then the CUDA tests. Every step is
# capped so that the whole run ends within END seconds (default 540); logs and JSON go to $OUT (default
# ./gpu-check-out), and a summary is printed last. Where gymnasium is missing, carry its wheels in .whl/.
export PYTHONUNBUFFERED=1
END=${END:-540}
OUT=${OUT:-gpu-check-out}
mkdir -p "$OUT"
T0=$(date +%s)
if compgen -G ".whl/*.whl" > /dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=${PYTHONPATH:+$PYTHONPATH:}$PWD
left() { echo $(( END - ($(date +%s) - T0) )); }
step() {  # step NAME MAX_SECONDS command...
  local name=$1 cap=$2; shift 2
  local t; t=$(left); (( t > cap )) && t=$cap
  if (( t < 20 )); then echo "[skip $name: $(left) s left]" | tee -a "$OUT/summary.txt"; return; fi
  local s; s=$(date +%s)
  timeout "$t" "$@" > "$OUT/$name.log" 2>&1
  echo "[$name: rc $? after $(( $(date +%s) - s )) s, cap $t s]" | tee -a "$OUT/summary.txt"
}
{ nvidia-smi -L; python3 -c "import torch, sys; print('torch', torch.__version__, 'python', sys.version.split()[0], torch.cuda.get_device_name())"; } 2>&1 | tee "$OUT/summary.txt"
BENCH="python3 -m torchtraj.bench --problems pendulum --device cuda --no-reference --method ipm --batch 1024 65536 --launches"
step ipm_eager 150 $BENCH --json "$OUT/ipm_eager.json"
step ipm_graphs 300 $BENCH --cuda-graphs --json "$OUT/ipm_graphs.json"
step tests 120 python3 -m pytest -p no:cacheprovider -n 4 -q tests/test_bench_launches.py \
  tests/test_envs.py::test_vector_env_on_cuda_matches_cpu tests/test_ilqr.py::test_runs_on_cuda \
  tests/test_implicit.py::test_cuda_gradients_match_cpu tests/test_interior_point.py::test_cuda_graphs_replay_the_eager_solve
for f in ipm_eager ipm_graphs; do
  echo "== $f"; grep -E "^(pendulum|throughput|  launches|  \(the)|rror|without a CUDA graph" "$OUT/$f.log" | cut -c1-400 | tail -12
done
echo "== tests"; grep -E "^(FAILED|ERROR|E  )" "$OUT/tests.log" | cut -c1-300 | head -30; tail -3 "$OUT/tests.log"
cat "$OUT/summary.txt"
