#!/usr/bin/env bash
# Can another host reach the gate's DDS sockets when `only-networks = ["127.0.0.1"]`?
# (issue 51 item 4, docs/reliability.md). Two network namespaces joined by a veth pair:
# "pc" (10.231.0.1/24) runs the real guardian-gate binary (a controller domain of its own,
# so two DDS participants; no guardiand: the gate fails closed and keeps running), "other"
# (10.231.0.2/24) is another host on the same link. For every UDP port the gate holds, a
# datagram is sent on a connected UDP socket
#   - from "other" to 10.231.0.1:<port>: ECONNREFUSED (ICMP port unreachable: no socket
#     took it) passes; a timeout (a socket took it silently) fails;
#   - from inside "pc" to 127.0.0.1:<port> (the control: the port really is bound): a
#     timeout passes; refused fails.
# Needs root (ip netns) and the guardian-gate binary of `cargo test --workspace`
# (target/debug), or a binary given as the first argument. Skips, loudly, only where
# `ip netns add` is not permitted. .ci/run calls this.
set -euo pipefail
cd "$(dirname "$0")/../../.."
target=${CARGO_TARGET_DIR:-target}
gate_bin=$(realpath "${1:-$target/debug/guardian-gate}")
[ -x "$gate_bin" ] || { echo "no guardian-gate binary at $gate_bin" >&2; exit 1; }

pc=gpc$$
other=goth$$
if ! ip netns add "$pc" 2>/dev/null; then
  echo "######## SKIPPED: 'ip netns add' is not permitted here (needs root); the gate's" >&2
  echo "######## socket restriction (only-networks) was NOT tested." >&2
  exit 0
fi
tmp=$(mktemp -d)
gate_pid=
cleanup() {
  set +e
  if [ -n "$gate_pid" ]; then
    kill "$gate_pid" 2>/dev/null
    wait "$gate_pid" 2>/dev/null
  fi
  ip netns del "$pc" 2>/dev/null || true
  ip netns del "$other" 2>/dev/null || true
  rm -rf "$tmp"
}
trap cleanup EXIT
ip netns add "$other"
ip link add "vp$$" netns "$pc" type veth peer name "vo$$" netns "$other"
ip -n "$pc" addr add 10.231.0.1/24 dev "vp$$"
ip -n "$other" addr add 10.231.0.2/24 dev "vo$$"
for ns in "$pc" "$other"; do
  ip -n "$ns" link set lo up
done
ip -n "$pc" link set "vp$$" up
ip -n "$other" link set "vo$$" up
# ICMP port unreachable is rate limited per peer (a burst of 6, then one a second); every
# probe must get its answer.
ip netns exec "$pc" sysctl -qw net.ipv4.icmp_ratelimit=0

cat >"$tmp/gate.toml" <<TOML
gate = "/netns_gate"
controller = "/netns_ctrl"
domain-id = 7
controller-domain-id = 8
only-networks = ["127.0.0.1"]
[guardiand]
service-name = "guardian-netns-test/$$/none"
TOML
ip netns exec "$pc" env -u RUST_LOG "$gate_bin" --config "$tmp/gate.toml" 2>"$tmp/gate.log" &
gate_pid=$!

# The gate's UDP ports, once its two participants are up (5 sockets each) and the count
# has stayed the same for a second; at most 30 s.
ports() {
  ip netns exec "$pc" ss -Huanp | grep "pid=$gate_pid," | awk '{print $4}' | sed 's/.*://' | sort -n
}
prev=-1
for _ in $(seq 60); do
  kill -0 "$gate_pid" 2>/dev/null || { echo "the gate exited:" >&2; cat "$tmp/gate.log" >&2; exit 1; }
  n=$(ports | wc -l)
  [ "$n" -ge 10 ] && [ "$n" -eq "$prev" ] && break
  prev=$n
  sleep 0.5
done
ip netns exec "$pc" ss -Huanp | grep "pid=$gate_pid," | awk '{print "  socket", $4}'
mapfile -t gate_ports < <(ports)
[ "${#gate_ports[@]}" -ge 10 ] || { echo "only ${#gate_ports[@]} UDP sockets (expected 10)" >&2; cat "$tmp/gate.log" >&2; exit 1; }

# One datagram on a connected UDP socket, then wait 1 s for anything back.
probe='
import socket, sys
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.settimeout(1.0)
s.connect((sys.argv[1], int(sys.argv[2])))
s.send(b"guardian netns probe")
try:
    s.recv(64)
    print("answered")
except ConnectionRefusedError:
    print("refused")
except socket.timeout:
    print("reached")
'
refused_remote=0
reached_local=0
failures=0
printf '%-7s %-28s %-28s %s\n' port "from other (10.231.0.1)" "from pc (127.0.0.1)" result
for port in "${gate_ports[@]}"; do
  remote=$(ip netns exec "$other" python3 -c "$probe" 10.231.0.1 "$port")
  local_=$(ip netns exec "$pc" python3 -c "$probe" 127.0.0.1 "$port")
  ok=ok
  [ "$remote" = refused ] && refused_remote=$((refused_remote + 1)) || ok=FAIL
  [ "$local_" != refused ] && reached_local=$((reached_local + 1)) || ok=FAIL
  [ "$ok" = ok ] || failures=$((failures + 1))
  printf '%-7s %-28s %-28s %s\n' "$port" "$remote" "$local_" "$ok"
done
n=${#gate_ports[@]}
echo "$refused_remote of $n ports refused from another host, $reached_local of $n reachable on loopback"
grep "DDS sockets restricted" "$tmp/gate.log" | sed 's/^/  gate: /' || true
if [ "$failures" -ne 0 ]; then
  echo "FAILED: $failures of $n ports" >&2
  exit 1
fi
