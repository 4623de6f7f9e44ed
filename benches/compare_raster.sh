#!/usr/bin/env bash
# Side by side on one machine: `bench raster` of this checkout and of an
# earlier commit (built from `git archive` in its own target directory), in
# alternating rounds, with the load average before each round. `bench raster`
# runs 1 thread and every core (both versions: no --threads here); this checkout
# also prints its stage times.
#
#   benches/compare_raster.sh OLD_COMMIT [ROUNDS=3] [REPS=5]
set -euo pipefail
old=${1:?usage: benches/compare_raster.sh OLD_COMMIT [ROUNDS] [REPS]}
rounds=${2:-3}
reps=${3:-5}
. "$(dirname "$0")/build_both.sh"
table() { grep -E '^(scene|[0-9]+x[0-9]+ )'; }
for r in $(seq 1 "$rounds"); do
    echo "== round $r, load average: $(cut -d' ' -f1-3 /proc/loadavg)"
    echo "-- $old"
    "$old_bin" bench raster --reps "$reps" | table
    echo "-- this checkout ($(git -C "$root" rev-parse --short HEAD)), load average: $(cut -d' ' -f1-3 /proc/loadavg)"
    "$new_bin" bench raster --reps "$reps" | grep -v -E '^(machine|f32 FMA|instruction|\(f32)'
done
