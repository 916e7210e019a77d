#!/usr/bin/env bash
# Interop of guardian-gate with Eclipse Cyclone DDS (PyPI cyclonedds, C library inside the
# wheel), using ROS 2's topic and type naming (gate/tests/cyclonedds/interop.py). Installs
# cyclonedds in a venv of its own under target/; needs the guardian-gate binary of
# `cargo test --workspace` (target/debug). .ci/run calls this.
set -euo pipefail
cd "$(dirname "$0")/../../.."
target=${CARGO_TARGET_DIR:-target}
venv=$target/cyclonedds-venv
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
"$venv/bin/pip" install -q cyclonedds==11.0.1
"$venv/bin/python" gate/tests/cyclonedds/interop.py "$(realpath "$target/debug/guardian-gate")"
