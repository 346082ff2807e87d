#!/usr/bin/env bash
# Planner step cost before/after in the same run: bench_planner_step.py on the planning code of git ref REF and
# on the working tree, in alternating processes (PAIRS times), so load on a shared machine hits both alike.
#
#   benchmarks/compare_planner_step.sh REF [ROUNDS] [PAIRS]     e.g. benchmarks/compare_planner_step.sh 0dc893d 2 2
#
# REF's apf_companion/ is exported with `git archive` into a temporary directory and put first on PYTHONPATH (it
# then wins over the venv's editable install of the working tree). The benchmark script, sim/ and the venv are
# the working tree's. Prints, per run, the bapf-nav, cr-bapf*
# and bendyruler rows (2D, 30 and 300 points: median / quiet median in us) and the issue-7 target line.
# Not part of `./dev bench` (it needs a second version of the code).
set -euo pipefail
cd "$(dirname "$0")/.."
ref=${1:?usage: benchmarks/compare_planner_step.sh REF [ROUNDS] [PAIRS]}
rounds=${2:-2}
pairs=${3:-2}
root=$PWD
python=${APF_VENV:-$root/.venv}/bin/python
base=$(mktemp -d)
trap 'rm -rf "$base"' EXIT
git archive "$ref" apf_companion | tar -x -C "$base"
export OPENBLAS_NUM_THREADS=1
run() {  # run LABEL [PYTHONPATH]
  local out
  out=$(PYTHONPATH=${2:-} "$python" "$root/benchmarks/bench_planner_step.py" --rounds "$rounds")
  echo "== $1: $(grep '^before:' <<<"$out")"
  grep -E '^\| (cr-bapf\*|bapf-nav|bendyruler) \| 2D \| (30|300) \|' <<<"$out" | awk -F'|' '{for (i = 2; i <= 7; i++) gsub(/ /, "", $i); printf "  %-10s %3s points: median %s us, quiet median %s us\n", $2, $4, $5, $7}'
  grep '^issue 7' <<<"$out" | sed 's/^/  /'
}
for _ in $(seq "$pairs"); do
  run "$ref" "$base"
  run "working tree" ""
done
