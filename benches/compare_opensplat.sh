#!/usr/bin/env bash
# Side by side on one machine: OpenSplat's CPU rasterizer (single-threaded,
# untiled; built from an OpenSplat checkout against the pip torch package's
# libtorch) and liquid-splat's, forward and backward, on the same Gaussians,
# cameras and output gradients: a D-NeRF scene at DOWNSCALE, its first
# CAMERAS training cameras, one seeded output gradient per camera, in one
# state per entry of STEPS: 0 is the initial Gaussians (as the rasterizer
# receives them during warm-up), S > 0 the Gaussians after S training
# iterations (`liquid-splat train --iterations S --seed 0`, CfC field D6
# W128), deformed at each camera's time. Checks that the two agree in every
# state (tolerances in benches/opensplat_harness.cpp, explained in
# benches/README.md) and prints one row per state.
#
#   benches/compare_opensplat.sh OPENSPLAT_DIR DNERF_SCENE_DIR [REPS=3] [POINTS=20000] [CAMERAS=10] [DOWNSCALE=2] [STEPS="0 250"]
#
# With PIN_THREADS=1 in the environment, liquid-splat's workers are pinned
# one per CPU (as `--pin-threads`).
#
# OPENSPLAT_DIR: a checkout of github.com/pierotofy/OpenSplat (measured with
# 1.1.5); only rasterizer/gsplat-cpu is compiled. Needs python3 with torch
# and a C++20 compiler that builds libtorch's headers (CXX, default
# clang++). Exit status: 0 when the two agree, 1 when they do not, 2 on
# unusable input.
set -euo pipefail
usage="usage: benches/compare_opensplat.sh OPENSPLAT_DIR DNERF_SCENE_DIR [REPS] [POINTS] [CAMERAS] [DOWNSCALE] [STEPS]"
opensplat=${1:?$usage}
data=${2:?$usage}
reps=${3:-3}
points=${4:-20000}
cameras=${5:-10}
downscale=${6:-2}
steps_list=${7:-0 250}
for s in $steps_list; do
    case $s in
    '' | *[!0-9]*)
        echo "STEPS: '$s' is not a non-negative integer (a list such as \"0 250\")" >&2
        exit 2
        ;;
    esac
done
cxx=${CXX:-clang++}
if [ ! -f "$opensplat/rasterizer/gsplat-cpu/gsplat_cpu.cpp" ]; then
    echo "$opensplat: not an OpenSplat checkout (no rasterizer/gsplat-cpu/gsplat_cpu.cpp)" >&2
    exit 2
fi
torch=$(python3 -c 'import os, torch; print(os.path.dirname(torch.__file__))') || {
    echo "python3 cannot import torch (needed for libtorch)" >&2
    exit 2
}
root=$(git rev-parse --show-toplevel)
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

echo "building the OpenSplat harness ($cxx, OpenSplat $(cat "$opensplat/VERSION" 2>/dev/null || echo '?'), libtorch $(python3 -c 'import torch; print(torch.__version__)'))"
"$cxx" -O3 -std=c++20 -I"$opensplat" -I"$torch/include" -I"$torch/include/torch/csrc/api/include" \
    "$root/benches/opensplat_harness.cpp" "$opensplat/rasterizer/gsplat-cpu/gsplat_cpu.cpp" \
    -o "$tmp/harness" -L"$torch/lib" -Wl,-rpath,"$torch/lib" -ltorch -ltorch_cpu -lc10
echo "building liquid-splat's side (cargo bench --bench opensplat_scene)"
cargo bench --quiet --manifest-path "$root/Cargo.toml" --bench opensplat_scene --no-run

echo "machine: $(grep -m1 'model name' /proc/cpuinfo 2>/dev/null | cut -d: -f2 | sed 's/^ //'), $(nproc) CPUs"
echo "threads: OpenSplat 1 (torch::set_num_threads(1), OMP_NUM_THREADS=1); liquid-splat 1 and 2 (rayon pools$([ "${PIN_THREADS:-}" = 1 ] && echo ', pinned'))"
status=0
for steps in $steps_list; do
    dir="$tmp/state$steps"
    echo
    echo "== state: $([ "$steps" -eq 0 ] && echo initial || echo "after $steps training steps") =="
    echo "load average before: $(cut -d' ' -f1-3 /proc/loadavg)"
    cargo bench --quiet --manifest-path "$root/Cargo.toml" --bench opensplat_scene -- \
        "$data" "$dir/scene" "$downscale" "$points" "$cameras" "$reps" "$steps" | tee "$dir.ls.txt"
    echo "load average between: $(cut -d' ' -f1-3 /proc/loadavg)"
    st=0
    OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 "$tmp/harness" "$dir/scene" "$reps" | tee "$dir.os.txt" || st=$?
    echo "load average after: $(cut -d' ' -f1-3 /proc/loadavg)"
    if [ "$st" -ne 0 ] && [ "$st" -ne 1 ]; then
        exit "$st"
    fi
    [ "$st" -eq 1 ] && status=1
    rm -rf "$dir/scene"
done

# key=value fields of the line starting with $2 in file $1.
field() { awk -v p="$2" -v k="$3" '$0 ~ "^"p { for (i = 1; i <= NF; i++) { split($i, a, "="); if (a[1] == k) print a[2] } }' "$1"; }
for kind in wall cpu; do
    sfx=$([ "$kind" = cpu ] && echo _cpu_ms || echo _ms)
    echo
    if [ "$kind" = cpu ]; then
        echo "CPU time (all threads; for 2 threads CPU time / 2 estimates the wall time on an idle machine), ms, sum over $cameras cameras of the mean of $reps runs:"
    else
        echo "wall time, ms, sum over $cameras cameras of the fastest of $reps runs:"
    fi
    echo "| state | OpenSplat, 1 thread, fwd / bwd / total | liquid-splat, 1 thread | liquid-splat, 2 threads$([ "$kind" = cpu ] && echo ' (CPU time / 2)') | OpenSplat total / liquid-splat total, 1 / 2 threads |"
    echo "|---|---|---|---|---|"
    for steps in $steps_list; do
        dir="$tmp/state$steps"
        label=$([ "$steps" -eq 0 ] && echo initial || echo "after $steps training steps")
        of=$(field "$dir.os.txt" "opensplat threads=1" "fwd$sfx"); ob=$(field "$dir.os.txt" "opensplat threads=1" "bwd$sfx")
        l1f=$(field "$dir.ls.txt" "liquid-splat threads=1" "fwd$sfx"); l1b=$(field "$dir.ls.txt" "liquid-splat threads=1" "bwd$sfx")
        l2f=$(field "$dir.ls.txt" "liquid-splat threads=2" "fwd$sfx"); l2b=$(field "$dir.ls.txt" "liquid-splat threads=2" "bwd$sfx")
        awk -v l="$label" -v o="$of" -v ob="$ob" -v a="$l1f" -v ab="$l1b" -v b="$l2f" -v bb="$l2b" -v k="$kind" 'BEGIN {
            d = (k == "cpu") ? 2 : 1
            b /= d; bb /= d
            printf "| %s | %.0f / %.0f / %.0f ms | %.0f / %.0f / %.0f ms | %.0f / %.0f / %.0f ms | %.1fx / %.1fx |\n",
                l, o, ob, o + ob, a, ab, a + ab, b, bb, b + bb, (o + ob) / (a + ab), (o + ob) / (b + bb)
        }'
    done
done
echo
echo "round trip of one cache line between liquid-splat's two workers just before / after its two-thread timed runs (40-50 ns in the development VM's quiet minutes, 320-450 ns in its slow periods; benches/README.md):"
for steps in $steps_list; do
    dir="$tmp/state$steps"
    label=$([ "$steps" -eq 0 ] && echo initial || echo "after $steps training steps")
    echo "  $label: $(field "$dir.ls.txt" "liquid-splat threads=2" xcpu_before_ns) / $(field "$dir.ls.txt" "liquid-splat threads=2" xcpu_after_ns) ns"
done
echo
echo "agreement: $([ "$status" -eq 0 ] && echo "ok in every state" || echo "FAILED (see the per-camera tables above)")"
exit "$status"
