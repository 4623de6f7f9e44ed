#!/usr/bin/env bash
# Side by side on one machine: `bench deform` of this checkout and of an
# earlier commit (built from `git archive` in its own target directory), and
# PyTorch's CPU build (python/bench_deform.py, when torch is installed),
# in alternating rounds, with the load average before each round.
#
#   benches/compare_deform.sh OLD_COMMIT [ROUNDS=3] [REPS=7] [THREADS=2] [N=20000]
#
# Then the per-operation profiles and the kernel table of this checkout once.
set -euo pipefail
old=${1:?usage: benches/compare_deform.sh OLD_COMMIT [ROUNDS] [REPS] [THREADS] [N]}
rounds=${2:-3}
reps=${3:-7}
threads=${4:-2}
n=${5:-20000}
. "$(dirname "$0")/build_both.sh"
summary() { awk 'NF == 0 { done = 1 } !done'; }
for r in $(seq 1 "$rounds"); do
    echo "== round $r, load average: $(cut -d' ' -f1-3 /proc/loadavg)"
    echo "-- $old"
    "$old_bin" --threads "$threads" bench deform --n "$n" --reps "$reps" | summary
    echo "-- this checkout ($(git -C "$root" rev-parse --short HEAD))"
    "$new_bin" --threads "$threads" bench deform --n "$n" --reps "$reps" | summary
    if python3 -c 'import torch' 2>/dev/null; then
        echo "-- PyTorch CPU"
        python3 "$root/python/bench_deform.py" --threads "$threads" --n "$n" --reps "$reps"
    fi
done
echo "== this checkout: profiles and kernels"
"$new_bin" --threads "$threads" bench deform --n "$n" --reps "$reps" | awk 'f; NF == 0 { f = 1 }'
