#!/usr/bin/env bash
# Interop of guardian-gate with eProsima Fast DDS (Debian's libfastrtps 2.9, the DDS behind
# ROS 2 Jazzy's default RMW), with ROS 2's topic and type names and the enhanced service
# mapping (gate/tests/fastdds/interop.cpp). Installs what it needs (packaging/deps.sh
# fastdds: libfastrtps-dev, fastddsgen, g++), generates the C++ types of ros2.idl and builds
# the participant under target/fastdds; needs the guardian-gate binary of `cargo test
# --workspace` (target/debug). Starts the gate on loopback with a domain of its own and no
# guardiand, runs the participant, stops the gate. .ci/run calls this.
set -euo pipefail
cd "$(dirname "$0")/../../.."
bash packaging/deps.sh fastdds
target=${CARGO_TARGET_DIR:-target}
out=$target/fastdds
src=gate/tests/fastdds
mkdir -p "$out"
if [ ! -x "$out/fastdds-interop" ] || [ "$src/interop.cpp" -nt "$out/fastdds-interop" ] || [ "$src/ros2.idl" -nt "$out/fastdds-interop" ]; then
  fastddsgen -replace -d "$out" "$src/ros2.idl" >"$out/fastddsgen.log" 2>&1 || { cat "$out/fastddsgen.log"; exit 1; }
  g++ -std=c++17 -O1 -I"$out" -o "$out/fastdds-interop" "$src/interop.cpp" "$out/ros2.cxx" "$out/ros2PubSubTypes.cxx" -lfastrtps -lfastcdr
fi
gate_bin=$(realpath "$target/debug/guardian-gate")
tmp=$(mktemp -d)
domain=$((60 + $$ % 30))
ns="/fastdds_gate_$$"
executive="/fastdds_executive"
cat >"$tmp/gate.toml" <<TOML
gate = "$ns"
controller = "/fastdds_ctrl_$$"
domain-id = $domain
only-networks = ["127.0.0.1"]
claim-from = ["$executive"]
[guardiand]
service-name = "guardian-fastdds-test/$$/none"
TOML
env -u RUST_LOG "$gate_bin" --config "$tmp/gate.toml" 2>"$tmp/gate.log" &
gate_pid=$!
status=0
timeout 120 "$out/fastdds-interop" "$domain" "$ns" "$executive" || status=$?
kill "$gate_pid" 2>/dev/null || true
wait "$gate_pid" 2>/dev/null || true
if [ "$status" -ne 0 ]; then
  echo "--- the gate's log:" >&2
  tail -n 40 "$tmp/gate.log" >&2
fi
rm -rf "$tmp"
exit "$status"
