#!/usr/bin/env bash
# The Python package's gate, called by .ci/run after the workspace's tests: format and lint
# the extension crate, build the abi3 wheel with maturin, install it into a fresh venv
# (maturin, numpy and pytest from PyPI) and run the pytest suite against real guardiand
# processes on a dataset of Latin drawings made by `guardian-lab dataset`.
#
# Needs python3 with the venv module (Debian: python3-venv) and ../shared/omniglot/strokes.
# Uses the workspace's target directory, so dependencies built by `cargo test --workspace`
# (dev profile) are reused. PYTHON overrides the interpreter.
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
export CARGO_TARGET_DIR="$repo/target"
python=${PYTHON:-python3}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

echo "-- fmt, clippy (python/)"
cargo fmt --manifest-path python/Cargo.toml --check
cargo clippy --manifest-path python/Cargo.toml --all-targets -- -D warnings

echo "-- fresh venv"
"$python" -m venv "$work/venv"
venv_py="$work/venv/bin/python"
"$venv_py" -m pip install -q --disable-pip-version-check "maturin>=1.16,<1.17" numpy pytest

echo "-- wheel"
(cd python && "$work/venv/bin/maturin" build --out "$work/wheels" -i "$venv_py")
wheel=$(ls "$work"/wheels/guardian-*-abi3-*.whl)
"$venv_py" -m pip install -q --disable-pip-version-check "$wheel"

echo "-- binaries and data"
cargo build -p guardian-daemon -p guardian-ctl -p guardian-lab --bins
mkdir -p "$work/strokes"
ln -s "$repo/../shared/omniglot/strokes/Latin" "$work/strokes/Latin"
"$CARGO_TARGET_DIR/debug/guardian-lab" dataset --strokes "$work/strokes" --out "$work/latin.safetensors" --quiet

echo "-- pytest"
export GUARDIAND_BIN="$CARGO_TARGET_DIR/debug/guardiand"
export GUARDIANCTL_BIN="$CARGO_TARGET_DIR/debug/guardianctl"
export GUARDIAN_MODEL="$repo/models/embedder.safetensors"
export GUARDIAN_DATASET="$work/latin.safetensors"
# From the work directory, so `import guardian` is the installed wheel, not the source tree.
status=0
(cd "$work" && "$venv_py" -m pytest -v -p no:cacheprovider "$repo/python/tests") || status=$?
if [ "$status" -eq 5 ]; then
  echo "python/ci.sh: pytest collected no tests (exit status 5): failing"
  exit 1
fi
exit "$status"
