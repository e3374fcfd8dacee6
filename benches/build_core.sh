#!/usr/bin/env bash
# Build one revision's extension the way the wheel is built, for the benches' --baseline and
# PYTHONPATH runs:
#
#     benches/build_core.sh REV DIR            # DIR/python: `import poisson_rs` loads REV's build
#     benches/build_core.sh REV DIR --cargo    # the cdylib-and-rlib build of `cargo build`
#
# `pip install .` (maturin) compiles the library as a cdylib alone:
# `cargo rustc --profile release --features python --lib --crate-type cdylib`. `cargo build
# --release` builds a cdylib and an rlib together, and with an rlib in the crate types cargo
# silently skips the profile's LTO, so its code is not the wheel's (docs/performance.md, "The
# build the benches time"). --cargo keeps that build for comparisons with earlier figures.
#
# DIR, which must not exist, gets a detached worktree of REV and its own target folder,
# DIR/target. Remove it afterwards with `git worktree remove --force DIR`.
set -euo pipefail

if [[ $# -lt 2 || $# -gt 3 || ( $# -eq 3 && "$3" != "--cargo" ) ]]; then
    echo "usage: $0 REV DIR [--cargo]" >&2
    exit 2
fi
rev=$1
dir=$2
kind=${3:-}

repo=$(git -C "$(dirname "$0")" rev-parse --show-toplevel)
git -C "$repo" rev-parse --verify --quiet "$rev^{commit}" > /dev/null \
    || { echo "$0: REV '$rev' is not a commit of $repo" >&2; exit 2; }
# Never built over: a folder there may hold someone's work.
if [[ -e "$dir" ]]; then
    echo "$0: DIR '$dir' exists; remove it first (git worktree remove --force '$dir')" >&2
    exit 2
fi
git -C "$repo" worktree add --detach --quiet "$dir" "$rev"

cd "$dir"
dir=$(pwd)
export CARGO_TARGET_DIR="$dir/target"
if [[ "$kind" == "--cargo" ]]; then
    cargo build --quiet --release --features python
else
    cargo rustc --quiet --profile release --features python --lib --crate-type cdylib
fi
cp "$CARGO_TARGET_DIR/release/libpoisson_rs.so" python/poisson_rs/_core.abi3.so
echo "$dir/python"
