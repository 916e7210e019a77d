#!/usr/bin/env bash
# The rosbags interop test (gate/tests/rosbags.rs): a bag written by the Python `rosbags`
# package (rosbag2 MCAP, ROS 2 Jazzy CDR) is enrolled by guardianctl. Installs rosbags in a
# venv of its own under target/, then runs the ignored test with it (with the workspace's
# feature set, so nothing is compiled again after `cargo test --workspace`). .ci/run calls this.
set -euo pipefail
cd "$(dirname "$0")/../../.."
venv=${CARGO_TARGET_DIR:-target}/rosbags-venv
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
"$venv/bin/pip" install -q rosbags==0.11.9
GUARDIAN_ROSBAGS_PYTHON="$(cd "$venv/bin" && pwd)/python" \
  cargo test --workspace --test rosbags -- --ignored
