#!/usr/bin/env bash
# Build the CUDA rasterizers that python/cuda_crosscheck.py compares the oracle with, from
# their pinned sources, with fast math off, in DIR:
#
#   DIR/inria        ingra14m/diff-gaussian-rasterization-extentions f2d8fa9 (the D-3DGS
#                    paper branch's rasterizer: Inria's 59f5f77 plus a depth output)
#   DIR/gsplat-1.5.3 nerfstudio-project/gsplat v1.5.3 (937e299)
#   DIR/gsplat-1.6   nerfstudio-project/gsplat c3d59bbb (1.6.0)
#
#   python/cuda_peers.sh DIR        # clones what is missing (with the glm submodule), builds
#
# Needs git, nvcc and a CUDA build of torch; TORCH_CUDA_ARCH_LIST picks the GPU (for example
# 9.0 for an H100 or H200). Changes made to the sources before building; apart from turning
# fast math off, none changes a computed value:
# - Inria: `#include <cstdint>` at the top of cuda_rasterizer/rasterizer_impl.h (recent GCC
#   no longer provides uint32_t through <iostream>); no fast math in its setup.py already.
# - gsplat 1.5.3: `--use_fast_math` removed from setup.py's nvcc flags (1.5.3 has no FAST_MATH
#   switch), and the rasterizers' template instantiations for channel counts other than 3
#   removed (`__INS__(n)` / `__LAUNCH_KERNEL__(n)` lines), which only shortens the build: the
#   comparisons render 3 channels.
# - gsplat 1.6: no change; built with FAST_MATH=0 BUILD_3DGS=1 NUM_CHANNELS=3
#   BUILD_EXPERIMENTAL=0 (its own switches: no fast math, the 3DGS kernels, 3 channels).
# nvcc still contracts multiply-adds into fused ones (its default, --fmad=true), which the
# oracle never does; NVCC_FLAGS=-fmad=false (read by both gsplat versions) turns that off too.
# Then, with the package installed (`pip install .` in this repository):
#   PYTHONPATH=DIR/inria        python python/cuda_crosscheck.py inria
#   PYTHONPATH=DIR/gsplat-1.5.3 python python/cuda_crosscheck.py gsplat --version 1.5.3
#   PYTHONPATH=DIR/gsplat-1.6   python python/cuda_crosscheck.py gsplat --version 1.6
set -euo pipefail
DIR=${1:?usage: python/cuda_peers.sh DIR}
GITHUB=${GITHUB:-https://github.com}
mkdir -p "$DIR"
cd "$DIR"

checkout() { # dir repo commit: clone if missing, then always check out the pinned commit
  [ -d "$1/.git" ] || git clone -q "$GITHUB/$2" "$1"
  git -C "$1" checkout -q "$3"
  git -C "$1" submodule update -q --init --recursive
  if [ "$(git -C "$1" rev-parse HEAD)" != "$(git -C "$1" rev-parse "$3^{commit}")" ]; then
    echo "$1 is not at $3" >&2
    exit 1
  fi
}

checkout inria ingra14m/diff-gaussian-rasterization-extentions f2d8fa9921ea9a6cb9ac1c33a34ebd1b11510657
checkout gsplat-1.5.3 nerfstudio-project/gsplat 937e29912570c372bed6747a5c9bf85fed877bae
checkout gsplat-1.6 nerfstudio-project/gsplat c3d59bbb54f91d1c93f1a80dc86960c696b4a059

h=inria/cuda_rasterizer/rasterizer_impl.h
grep -q '^#include <cstdint>' "$h" || sed -i '1i #include <cstdint>' "$h"
sed -i 's/"--use_fast_math", //' gsplat-1.5.3/setup.py
sed -i -E '/^\s*__(INS|LAUNCH_KERNEL)__\((1|2|4|5|8|9|16|17|32|33|64|65|128|129|256|257|512|513)\)\s*$/d' \
  gsplat-1.5.3/gsplat/cuda/csrc/*.cu gsplat-1.5.3/gsplat/cuda/csrc/Rasterization.cpp
if grep -q use_fast_math gsplat-1.5.3/setup.py; then
  echo "gsplat-1.5.3/setup.py still asks for fast math" >&2
  exit 1
fi

(cd inria && python setup.py build_ext --inplace)
(cd gsplat-1.5.3 && python setup.py build_ext --inplace)
(cd gsplat-1.6 && FAST_MATH=0 BUILD_3DGS=1 NUM_CHANNELS=3 BUILD_EXPERIMENTAL=0 \
  python setup.py build_ext --inplace)
echo "built: $PWD/inria, $PWD/gsplat-1.5.3, $PWD/gsplat-1.6 (put one on PYTHONPATH)"
