#!/usr/bin/env bash
# Side by side on one machine: OpenSplat's CPU rasterizer (single-threaded,
# untiled; built from an OpenSplat checkout against the pip torch package's
# libtorch) and liquid-splat's, forward and backward, on the same Gaussians,
# cameras and output gradients: a D-NeRF scene's initial Gaussians (as the
# rasterizer receives them during warm-up) at DOWNSCALE, its first CAMERAS
# training cameras, one seeded output gradient per camera. Checks that the
# two agree (tolerances in benches/opensplat_harness.cpp, explained in
# benches/README.md) and prints the table of milliseconds.
#
#   benches/compare_opensplat.sh OPENSPLAT_DIR DNERF_SCENE_DIR [REPS=3] [POINTS=20000] [CAMERAS=10] [DOWNSCALE=2]
#
# OPENSPLAT_DIR: a checkout of github.com/pierotofy/OpenSplat (measured with
# 1.1.5); only rasterizer/gsplat-cpu is compiled. Needs python3 with torch
# and a C++20 compiler that builds libtorch's headers (CXX, default
# clang++). Exit status: 0 when the two agree, 1 when they do not, 2 on
# unusable input.
set -euo pipefail
usage="usage: benches/compare_opensplat.sh OPENSPLAT_DIR DNERF_SCENE_DIR [REPS] [POINTS] [CAMERAS] [DOWNSCALE]"
opensplat=${1:?$usage}
data=${2:?$usage}
reps=${3:-3}
points=${4:-20000}
cameras=${5:-10}
downscale=${6:-2}
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
echo "load average before: $(cut -d' ' -f1-3 /proc/loadavg)"
cargo bench --quiet --manifest-path "$root/Cargo.toml" --bench opensplat_scene -- \
    "$data" "$tmp/scene" "$downscale" "$points" "$cameras" "$reps" | tee "$tmp/ls.txt"
echo "load average between: $(cut -d' ' -f1-3 /proc/loadavg)"
status=0
OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 "$tmp/harness" "$tmp/scene" "$reps" | tee "$tmp/os.txt" || status=$?
echo "load average after: $(cut -d' ' -f1-3 /proc/loadavg)"
if [ "$status" -ne 0 ] && [ "$status" -ne 1 ]; then
    exit "$status"
fi

# key=value fields of the line starting with $2 in file $1.
field() { awk -v p="$2" -v k="$3" '$0 ~ "^"p { for (i = 1; i <= NF; i++) { split($i, a, "="); if (a[1] == k) print a[2] } }' "$1"; }
row() { # label fwd bwd
    awk -v l="$1" -v f="$2" -v b="$3" 'BEGIN { printf "| %s | %.0f / %.0f / %.0f ms |", l, f, b, f + b }'
}
for kind in wall cpu; do
    sfx=$([ "$kind" = cpu ] && echo _cpu_ms || echo _ms)
    of=$(field "$tmp/os.txt" "opensplat threads=1" "fwd$sfx"); ob=$(field "$tmp/os.txt" "opensplat threads=1" "bwd$sfx")
    l1f=$(field "$tmp/ls.txt" "liquid-splat threads=1" "fwd$sfx"); l1b=$(field "$tmp/ls.txt" "liquid-splat threads=1" "bwd$sfx")
    l2f=$(field "$tmp/ls.txt" "liquid-splat threads=2" "fwd$sfx"); l2b=$(field "$tmp/ls.txt" "liquid-splat threads=2" "bwd$sfx")
    if [ "$kind" = cpu ]; then
        echo
        echo "CPU time (all threads; for 2 threads divide by 2 to estimate the wall time on an idle machine):"
    else
        echo
        echo "wall time, sum over $cameras cameras of the fastest of $reps runs:"
    fi
    echo "| side | fwd / bwd / total |"
    echo "|---|---|"
    row "OpenSplat, 1 thread" "$of" "$ob"; echo
    row "liquid-splat, 1 thread" "$l1f" "$l1b"; echo
    row "liquid-splat, 2 threads" "$l2f" "$l2b"; echo
    awk -v o="$of" -v ob="$ob" -v a="$l1f" -v ab="$l1b" -v b="$l2f" -v bb="$l2b" -v k="$kind" 'BEGIN {
        d = (k == "cpu") ? 2 : 1
        printf "OpenSplat total / liquid-splat total: %.1fx (1 thread), %.1fx (2 threads%s)\n",
            (o + ob) / (a + ab), (o + ob) / ((b + bb) / d), (k == "cpu") ? ", CPU time / 2" : ""
    }'
done
exit "$status"
