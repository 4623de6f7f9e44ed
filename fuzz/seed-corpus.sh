#!/usr/bin/env bash
# Write the seed corpora of the fuzz targets into fuzz/corpus/ (not committed:
# they are generated, the same bytes on every run): `case new` files of every
# stage (the same as tests/fuzz_replay.rs) plus the golden fixture inputs for
# `case_file`, the committed fixture datasets for `dataset`.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --quiet
bin=target/release/liquid-splat
cases=fuzz/corpus/case_file
mkdir -p "$cases" fuzz/corpus/dataset
k=0
while read -r args; do
  # shellcheck disable=SC2086
  set -- $args
  stage=$1; shift
  "$bin" case new "$stage" "$cases/seed$k.safetensors" "$@"
  k=$((k + 1))
done <<'LIST'
rasterize --width 16 --height 12 --count 6
rasterize --dtype f32 --width 16 --height 12 --count 6 --gradient inria
deform --count 5
deform --dtype f32 --field mlp --count 5 --6dof
loss --width 12 --height 11
step --width 16 --height 12 --count 6
step --dtype f32 --width 16 --height 12 --count 6 --field mlp
LIST
cp fixtures/cases/*.input.safetensors "$cases/"
cargo run --release --quiet --example fuzz_dataset_seeds -- fuzz/corpus/dataset
echo "seed corpus: $(ls "$cases" | wc -l) case files, $(ls fuzz/corpus/dataset | wc -l) datasets"
