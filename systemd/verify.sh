#!/usr/bin/env bash
# Checks the shipped systemd files with systemd's own tools (no running systemd needed):
# `systemd-analyze verify` on the unit (ExecStart pointed at a built guardiand, since verify
# requires the binary to exist), the exposure score of `systemd-analyze security` (fails above
# 2.0), and the sysusers.d and tmpfiles.d snippets through systemd-sysusers and
# systemd-tmpfiles into a scratch root (tmpfiles only as root, since it chowns).
# The same for guardian-gate.service, with the guardian-gate built beside guardiand.
# Usage: systemd/verify.sh [path/to/guardiand]   (default: target/debug/guardiand)
set -euo pipefail
cd "$(dirname "$0")/.."
bin=$(realpath "${1:-target/debug/guardiand}")
test -x "$bin" || { echo "verify.sh: $bin is not an executable; build guardiand first" >&2; exit 1; }
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
sed "s#^ExecStart=/usr/bin/guardiand#ExecStart=$bin#" systemd/guardiand.service > "$tmp/guardiand.service"
systemd-analyze verify "$tmp/guardiand.service"
echo "systemd-analyze verify: ok"
score=$(systemd-analyze security --offline=yes "$tmp/guardiand.service" 2>&1 | sed -n 's/.*Overall exposure level for guardiand.service: \([0-9.]*\).*/\1/p')
echo "systemd-analyze security exposure: $score"
awk -v s="$score" 'BEGIN { exit !(s != "" && s <= 2.0) }' || { echo "exposure above 2.0" >&2; exit 1; }
# guardian-gate.service the same way, with the guardian-gate built beside guardiand (it
# needs UDP for DDS and still stays within 2.0).
gate=$(dirname "$bin")/guardian-gate
test -x "$gate" || { echo "verify.sh: $gate is not an executable; build guardian-gate first" >&2; exit 1; }
sed "s#^ExecStart=/usr/bin/guardian-gate#ExecStart=$gate#" systemd/guardian-gate.service > "$tmp/guardian-gate.service"
systemd-analyze verify "$tmp/guardian-gate.service"
echo "systemd-analyze verify guardian-gate.service: ok"
score=$(systemd-analyze security --offline=yes "$tmp/guardian-gate.service" 2>&1 | sed -n 's/.*Overall exposure level for guardian-gate.service: \([0-9.]*\).*/\1/p')
echo "systemd-analyze security exposure (guardian-gate): $score"
awk -v s="$score" 'BEGIN { exit !(s != "" && s <= 2.0) }' || { echo "guardian-gate exposure above 2.0" >&2; exit 1; }
mkdir -p "$tmp/root/etc"
systemd-sysusers --root="$tmp/root" - < systemd/sysusers.d/guardian.conf
grep -q '^guardian:' "$tmp/root/etc/passwd" || { echo "sysusers did not create guardian" >&2; exit 1; }
echo "systemd-sysusers: ok ($(grep '^guardian:' "$tmp/root/etc/passwd"))"
if [ "$(id -u)" = 0 ]; then
  systemd-tmpfiles --root="$tmp/root" --create - < systemd/tmpfiles.d/guardian.conf
  uid=$(awk -F: '$1 == "guardian" { print $3 ":" $4 }' "$tmp/root/etc/passwd")
  for d in var/lib/guardian:700 run/guardian:711; do
    test "$(stat -c '%u:%g %a' "$tmp/root/${d%:*}")" = "$uid ${d#*:}" || { echo "tmpfiles: /${d%:*} is not guardian's, ${d#*:}" >&2; exit 1; }
  done
  echo "systemd-tmpfiles: ok (/var/lib/guardian 0700, /run/guardian 0711)"
fi
