#!/usr/bin/env bash
# Wall time of the README quick command's first run (an empty numba cache, so every kernel is
# compiled) and of a later run (kernels from that cache), N times each (default 3):
#     bash benchmarks/first_run.sh [N]        (MOEX=.venv/bin/moex if moex is not on the PATH)
# Each run writes into a temporary folder; the log's "ready in" lines say where compilation went.
set -euo pipefail
N=${1:-3}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
quick=(train task=lissajous2 train.experts.steps=300 train.gating.steps=200 num_runs=2 eval=quick)
for kind in first later; do
  for i in $(seq "$N"); do
    [ "$kind" = first ] && rm -rf "$work/cache"
    rm -rf "$work/out"
    start=$(date +%s.%N)
    NUMBA_CACHE_DIR="$work/cache" "${MOEX:-moex}" "${quick[@]}" hydra.run.dir="$work/out" > "$work/log" 2>&1
    end=$(date +%s.%N)
    printf '%s run %d: %.1f s wall; %s\n' "$kind" "$i" "$(awk "BEGIN {print $end - $start}")" \
      "$(grep -ho 'compiled [a-z0-9 -]* kernel ready in [0-9.]* s' "$work"/out/*.log | tr '\n' ';')"
  done
done
