#!/bin/bash
# Side-by-side loop timing of another revision (REF, e.g. main) and this working tree:
# bench_loop.py runs alternately on each, ROUNDS times, SECONDS each (nothing is written to
# docs/BENCHMARKS.md; copy the medians there by hand).
#
#   benchmarks/ab_loop.sh main 4 15
set -euo pipefail
ref=${1:?usage: benchmarks/ab_loop.sh REF [ROUNDS] [SECONDS]}
rounds=${2:-4}
seconds=${3:-15}
here=$(cd "$(dirname "$0")/.." && pwd)
py="$here/.venv/bin/python"
other=$(mktemp -d)
trap 'rm -rf "$other"' EXIT
git -C "$here" archive "$ref" | tar -x -C "$other"
for i in $(seq "$rounds"); do
  for side in "$ref" worktree; do
    dir=$here; [ "$side" = worktree ] || dir=$other
    echo "== $side round $i $(date +%T) load $(cut -d' ' -f1 /proc/loadavg)"
    (cd "$dir" && "$py" benchmarks/bench_loop.py --seconds "$seconds" --reps 1 --no-write 2>&1 | grep -E "^run|^bare|^C timer")
  done
done
