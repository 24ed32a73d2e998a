#!/usr/bin/env bash
# Before/after equivalence of a refactoring: runs the fixed grid (grid.toml) and the demo
# with the binary built from BASE (a commit) and with the working tree's, on this machine,
# and compares every episode record but its timings.
#   tools/equivalence/check.sh BASE
# Records are bit-identical only on one CPU model (README, "Reproducibility"), so both
# binaries run here, one after the other.
set -euo pipefail
base=${1:?usage: tools/equivalence/check.sh BASE_COMMIT}
root=$(cd "$(dirname "$0")/../.." && pwd)
work=$(mktemp -d)
trap 'git -C "$root" worktree remove --force "$work/base" >/dev/null 2>&1 || true; rm -rf "$work"' EXIT
git -C "$root" worktree add --detach "$work/base" "$base" >/dev/null
# The base builds in a target directory of its own: sharing the working tree's would let
# cargo's mtime fingerprints take the base's artifacts of the workspace crates for fresh ones.
(cd "$work/base" && CARGO_TARGET_DIR="$root/target/equivalence-base" cargo build --release --locked -q -p mte-cli)
cp "$root/target/equivalence-base/release/mte" "$work/mte-base"
(cd "$root" && cargo build --release --locked -q -p mte-cli)
run() { # binary, output directory
    "$1" --no-progress -q sweep "$root/tools/equivalence/grid.toml" --out "$2/grid" || true
    "$1" --no-progress -q sweep "$root/tools/equivalence/grid_image.toml" --out "$2/grid_image" || true
    "$1" --no-progress -q demo --episodes 2 --q 0,2 --out "$2/demo" \
        --policy "$root/assets/policies/pusht_keypoints_cpu" >/dev/null || true
}
run "$work/mte-base" "$work/before"
run "$root/target/release/mte" "$work/after"
status=0
for part in grid grid_image demo; do
    echo "== $part"
    python3 "$root/tools/equivalence/compare.py" "$work/before/$part" "$work/after/$part" || status=1
done
exit $status
