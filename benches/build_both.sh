# Sourced by the compare_*.sh scripts with `old` set to a commit: builds
# that commit (from `git archive`, in its own target directory under a
# temporary folder removed on exit) and this checkout, in release mode, and
# sets `root`, `tmp`, `old_bin` and `new_bin`; prints the machine.
root=$(git rev-parse --show-toplevel)
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
mkdir -p "$tmp/src"
git -C "$root" archive "$old" | tar -x -C "$tmp/src"
cargo build --release --quiet --manifest-path "$tmp/src/Cargo.toml" --target-dir "$tmp/target"
cargo build --release --quiet --manifest-path "$root/Cargo.toml"
old_bin="$tmp/target/release/liquid-splat"
new_bin="$root/target/release/liquid-splat"
echo "machine: $(grep -m1 'model name' /proc/cpuinfo 2>/dev/null | cut -d: -f2 | sed 's/^ //'), $(nproc) CPUs"
