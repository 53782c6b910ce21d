#!/usr/bin/env bash
# `livecap solve` in fresh processes, two trees alternating: wall and CPU (user+sys) seconds per run.
# usage: benchmarks/cli_ab.sh BEFORE_TREE AFTER_TREE TAKE PROFILE RIG REPEATS [cold]
# "cold" deletes AFTER_TREE's numba cache (solvers/__pycache__/*.nbi, *.nbc) before each of its runs.
set -euo pipefail
before=$1 after=$2 take=$3 profile=$4 rig=$5 reps=$6 cold=${7:-}
py=${PYTHON:-/work/main/.venv/bin/python}
out=$(mktemp -d)
run() {  # tree label
  local t0 t1
  t0=$(date +%s.%N)
  # from inside the tree: `python -m` puts the working directory first on sys.path, before PYTHONPATH
  (cd "$1" && /usr/bin/time -f "%U %S" -o "$out/time" env PYTHONPATH="$1" OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \
    "$py" -m livecap solve "$take" --rig "$rig" --profile "$profile" --out "$out/$2.csv" >/dev/null 2>&1)
  t1=$(date +%s.%N)
  echo "$2 wall $(echo "$t1 - $t0" | bc) cpu $(awk '{print $1 + $2}' "$out/time")"
}
for i in $(seq "$reps"); do
  run "$before" before
  if [ -n "$cold" ]; then rm -f "$after"/solvers/__pycache__/*.nbi "$after"/solvers/__pycache__/*.nbc; fi
  run "$after" after
done
cmp -s "$out/before.csv" "$out/after.csv" && echo "weights CSV: identical" || \
  echo "weights CSV: differ (compare with benchmarks.numba_ab's max |diff|)"
rm -rf "$out"
