#!/usr/bin/env bash
# Tests the Debian package for real on this machine (Debian, as root; CI runs it so):
#  1. builds it (packaging/build-deb.sh; arguments are passed on) and installs it with dpkg -i;
#  2. checks that every packaged file is installed and that every path the unit and the
#     config name exists (binary, config, model, default bank, user, state and runtime dirs);
#  3. runs the installed `guardiand --check` on the installed config as the service's user,
#     checks that the installed guardiand has fleet membership (`--fleet-keygen` writes a key
#     pair), and runs `systemd-analyze verify` on the installed unit;
#  4. starts the installed guardiand, enrolls a class with the installed guardianctl, stops it,
#     then installs the same package again: /var/lib/guardian/bank.gcb must stay untouched
#     (same bytes, same inode and mtime) and a local edit of the conffile must survive;
#  5. dpkg -r: only the state in /var/lib/guardian and the conffiles (guardiand's and
#     guardian-gate's) may remain (Debian keeps conffiles until purge); dpkg -P: nothing may
#     remain.
# It refuses to run over an existing installation, and an EXIT trap removes everything it
# made (package, files, the user if it created it, shared memory), on failure too.
# Usage: packaging/test-deb.sh [--profile PROFILE] [--no-build]   (default: --profile dev)
set -euo pipefail
cd "$(dirname "$0")/.."
start=$SECONDS

fail() { echo "test-deb: FAIL: $*" >&2; exit 1; }
step() { echo "-- $*"; }

[ "$(id -u)" = 0 ] || fail "needs root (dpkg -i)"
command -v dpkg >/dev/null || fail "needs dpkg"
[ $# -gt 0 ] || set -- --profile dev

# Everything the package creates; none may exist before (this is not a machine to test on
# if guardian is installed or was).
pkg=guardian
dirs=(/etc/guardian /var/lib/guardian /run/guardian /usr/share/guardian /usr/share/doc/guardian)
wants=/etc/systemd/system/multi-user.target.wants/guardiand.service
if dpkg-query -W -f='${db:Status-Status}' "$pkg" 2>/dev/null | grep -qv '^not-installed$'; then
  fail "package $pkg is installed here; remove it first (dpkg -P $pkg)"
fi
for d in "${dirs[@]}" "$wants"; do
  [ ! -e "$d" ] || fail "$d exists; this test would disturb an installation"
done
user_existed=0
getent passwd guardian >/dev/null && user_existed=1
prefix="gdebtest$$_"
tmp=$(mktemp -d)
daemon_pid=
gate_pid=

cleanup() {
  local rc=$?
  set +e
  [ -z "$gate_pid" ] || kill -KILL "$gate_pid" 2>/dev/null
  if [ -n "$daemon_pid" ] && kill -0 "$daemon_pid" 2>/dev/null; then
    kill -TERM "$daemon_pid"; sleep 1; kill -KILL "$daemon_pid" 2>/dev/null; wait "$daemon_pid" 2>/dev/null
  fi
  if dpkg-query -W -f='${db:Status-Status}' "$pkg" 2>/dev/null | grep -qv '^not-installed$'; then
    dpkg -P "$pkg" >/dev/null 2>&1 || dpkg -P --force-all "$pkg" >/dev/null 2>&1
  fi
  rm -rf "${dirs[@]}"
  rm -f "$wants" /dev/shm/"$prefix"*
  if [ "$user_existed" = 0 ] && getent passwd guardian >/dev/null; then
    userdel guardian || echo "test-deb: could not remove the user guardian" >&2
    getent group guardian >/dev/null && groupdel guardian
  fi
  rm -rf "$tmp"
  [ "$rc" = 0 ] || echo "test-deb: cleaned up after the failure" >&2
  exit "$rc"
}
trap cleanup EXIT

step "build ($*)"
deb=$(bash packaging/build-deb.sh "$@" | tail -n 1)
[ -f "$deb" ] || fail "no package at '$deb'"
echo "package: $deb ($(du -h "$deb" | cut -f1))"
# Packaged paths (files and symlinks), without the leading "./".
dpkg-deb -c "$deb" | awk '$1 !~ /^d/ { sub(/^\.\//, "", $6); print "/" $6 }' > "$tmp/files"
echo "files: $(wc -l < "$tmp/files")"

step "install (dpkg -i)"
dpkg -i "$deb" > "$tmp/dpkg.log" 2>&1 || { cat "$tmp/dpkg.log"; fail "dpkg -i"; }
while read -r f; do [ -e "$f" ] || fail "$f (in the package) is not installed"; done < "$tmp/files"

step "paths named by the unit and the config"
unit=/usr/lib/systemd/system/guardiand.service
conf=/etc/guardian/guardiand.toml
grep -qxF "$conf" /var/lib/dpkg/info/$pkg.conffiles || fail "$conf is not a conffile"
exec_start=$(sed -n 's/^ExecStart=//p' "$unit")
exe=${exec_start%% *}
[ -x "$exe" ] || fail "ExecStart binary $exe is missing"
unit_conf=$(sed -n 's/.*--config \([^ ]*\).*/\1/p' <<< "$exec_start")
[ "$unit_conf" = "$conf" ] || fail "the unit reads '$unit_conf', the package installs $conf"
user=$(sed -n 's/^User=//p' "$unit")
getent passwd "$user" >/dev/null || fail "User=$user does not exist"
[ "$(sed -n 's/^Group=//p' "$unit")" = "$user" ] && getent group "$user" >/dev/null || fail "Group= is not $user"
key() { sed -n "s/^$1 = \"\(.*\)\"$/\1/p" "$conf"; }
for k in model default-bank; do
  p=$(key "$k"); [ -f "$p" ] || fail "config $k = $p does not exist"; echo "$k: $p"
done
state=$(key state-dir)
root_path=$(key root-path)
[ "$(sed -n 's/^StateDirectory=//p' "$unit")" = "${state#/var/lib/}" ] || fail "StateDirectory= does not match state-dir = $state"
[ "$(sed -n 's/^RuntimeDirectory=//p' "$unit")" = "$(basename "$(dirname "$root_path")")" ] || fail "RuntimeDirectory= does not hold root-path = $root_path"
for d in "$state:700" "$(dirname "$root_path"):711"; do
  [ "$(stat -c '%U:%G %a' "${d%:*}")" = "$user:$user ${d#*:}" ] || fail "${d%:*} is $(stat -c '%U:%G %a' "${d%:*}"), not $user:$user ${d#*:}"
done
grep -q '^separation = true$' "$conf" || fail "the installed config does not turn admin separation on"
echo "state-dir: $state, iceoryx2 root-path: $root_path, user: $(getent passwd "$user")"

as_user() { setpriv --reuid="$user" --regid="$user" --init-groups env HOME="$state" "$@"; }

step "installed guardiand --check (as $user)"
as_user "$exe" --config "$conf" --check 2>"$tmp/check.err" | tee "$tmp/check.out" \
  || { cat "$tmp/check.err"; fail "guardiand --check"; }
grep -q '^ok: ' "$tmp/check.out" || fail "guardiand --check did not say ok"

step "installed guardiand has fleet membership (--fleet-keygen)"
keyout=$("$exe" --fleet-keygen "$tmp/fleet.key" 2>/dev/null) || fail "guardiand --fleet-keygen"
[[ "$keyout" =~ ^[0-9a-f]{64}$ ]] || fail "guardiand --fleet-keygen printed $keyout, not a public key"
[ "$(stat -c '%a' "$tmp/fleet.key")" = 600 ] || fail "the secret fleet key is not mode 0600"
[ "$(tr -d '\n' < "$tmp/fleet.key.pub")" = "$keyout" ] || fail "fleet.key.pub does not hold the printed key"
test -f /usr/share/doc/guardian/examples/guardiand-fleet.toml || fail "the fleet sample config is not installed"
echo "fleet key pair written; public key $keyout"

step "systemd-analyze verify $unit"
systemd-analyze verify "$unit" || fail "systemd-analyze verify"

step "enable offline (removal must undo it)"
if systemctl enable guardiand.service >/dev/null 2>&1 && [ -L "$wants" ]; then
  enabled=1; echo "enabled: $wants"
else
  enabled=0; echo "systemctl enable did not work here; skipped"
fi

step "enroll a class through the installed guardiand and guardianctl"
# The installed config with a prefix of its own for iceoryx2 (shared memory of this test only).
sed "s|^# prefix = \"iox2_\"|prefix = \"$prefix\"|" "$conf" > "$tmp/guardiand.toml"
grep -q "^prefix = \"$prefix\"" "$tmp/guardiand.toml" || fail "could not set the iceoryx2 prefix"
chmod 755 "$tmp"; chmod 644 "$tmp/guardiand.toml"
ctl() { as_user /usr/bin/guardianctl --iceoryx2-root-path "$root_path" --iceoryx2-prefix "$prefix" "$@"; }
# Started directly (not through a shell function), so $! is guardiand itself.
setpriv --reuid="$user" --regid="$user" --init-groups env HOME="$state" \
  "$exe" --config "$tmp/guardiand.toml" > "$tmp/daemon.log" 2>&1 &
daemon_pid=$!
for _ in $(seq 1 120); do
  kill -0 "$daemon_pid" 2>/dev/null || { cat "$tmp/daemon.log"; fail "guardiand exited"; }
  ctl status > /dev/null 2>&1 && break
  sleep 0.5
done
ctl status > /dev/null || { cat "$tmp/daemon.log"; fail "guardiand did not answer"; }
# Three valid Panda joint paths near the ready pose (q1..q7,tool per line).
for e in 1 2 3; do
  awk -v e="$e" 'BEGIN {
    split("0 -0.785 0 -2.356 0 1.571 0.785", r, " ");
    for (i = 0; i < 80; i++) {
      t = i / 79; line = "";
      for (j = 1; j <= 7; j++) line = line sprintf("%.5f,", r[j] + (0.2 + 0.01 * e) * sin(6.2832 * t + j + 0.05 * e));
      print line (t < 0.5 ? 1 : 0);
    } }' > "$tmp/example$e.csv"
done
chmod 644 "$tmp"/example*.csv
# Admin separation is on: the planners' user is refused, root enrolls through the admin socket.
if ctl enroll deb-test-class "$tmp"/example{1,2,3}.csv 2> "$tmp/refused.err"; then
  fail "the guardian user (a planner) could enroll"
fi
grep -q "not permitted" "$tmp/refused.err" || { cat "$tmp/refused.err"; fail "the planner's enroll was not refused as not permitted"; }
echo "planner enroll refused: $(grep -m1 "not permitted" "$tmp/refused.err")"
/usr/bin/guardianctl enroll deb-test-class "$tmp"/example{1,2,3}.csv || fail "root could not enroll through the admin socket"
ctl classes | grep -q deb-test-class || fail "the enrolled class is not listed"

step "the installed guardian-gate reaches the installed guardiand (DDS on loopback only)"
gate_conf=/etc/guardian/guardian-gate.toml
sed -e 's|^only-networks = \[\]|only-networks = ["127.0.0.1"]|' \
  -e "s|^# domain-id = 0|domain-id = $((150 + $$ % 50))|" \
  -e "s|^# iceoryx2-prefix = \"iox2_\"|iceoryx2-prefix = \"$prefix\"|" "$gate_conf" > "$tmp/gate.toml"
for want in '^only-networks = \["127.0.0.1"\]' '^domain-id = ' "^iceoryx2-prefix = \"$prefix\""; do
  grep -q "$want" "$tmp/gate.toml" || fail "could not set $want in the gate's config"
done
chmod 644 "$tmp/gate.toml"
setpriv --reuid="$user" --regid="$user" --init-groups env HOME="$state" \
  /usr/bin/guardian-gate --config "$tmp/gate.toml" > "$tmp/gate.log" 2>&1 &
gate_pid=$!
for _ in $(seq 1 60); do
  kill -0 "$gate_pid" 2>/dev/null || { cat "$tmp/gate.log"; fail "guardian-gate exited"; }
  grep -q "guardiand reachable" "$tmp/gate.log" && break
  sleep 0.5
done
grep -q "guardiand reachable" "$tmp/gate.log" || { cat "$tmp/gate.log"; fail "guardian-gate did not reach guardiand"; }
echo "gate: $(grep -m1 "guardiand reachable" "$tmp/gate.log")"
kill -TERM "$gate_pid"
rc=0; wait "$gate_pid" || rc=$?
[ "$rc" = 0 ] || { cat "$tmp/gate.log"; fail "guardian-gate did not stop cleanly (exit status $rc)"; }
gate_pid=
kill -TERM "$daemon_pid"
rc=0; wait "$daemon_pid" || rc=$?
[ "$rc" = 0 ] || { cat "$tmp/daemon.log"; fail "guardiand did not stop cleanly (exit status $rc)"; }
daemon_pid=
bank=$state/bank.gcb
[ -f "$bank" ] || fail "$bank was not written"
as_user "$exe" --config "$conf" --check 2>/dev/null | tee "$tmp/check2.out"
classes_before=$(sed -n 's/.* with \([0-9]*\) classes$/\1/p' "$tmp/check2.out")
grep -q "$bank" "$tmp/check2.out" || fail "--check does not load the persisted bank"

step "reinstall the same version over the enrolled bank"
before=$(sha256sum "$bank"; stat -c '%i %Y %U:%G %a %s' "$bank")
echo "# local edit kept across reinstalls" >> "$conf"
dpkg -i "$deb" > "$tmp/dpkg.log" 2>&1 || { cat "$tmp/dpkg.log"; fail "dpkg -i (again)"; }
after=$(sha256sum "$bank"; stat -c '%i %Y %U:%G %a %s' "$bank")
[ "$before" = "$after" ] || fail "reinstall touched $bank: $before -> $after"
grep -q '^# local edit kept across reinstalls$' "$conf" || fail "reinstall overwrote the edited conffile"
as_user "$exe" --config "$conf" --check 2>/dev/null | grep -q " with $classes_before classes$" \
  || fail "the bank lost classes"
echo "bank.gcb untouched ($classes_before classes, sha256 ${before:0:16}); conffile edit kept"

step "dpkg -r: only the state and the conffiles remain"
dpkg -r "$pkg" > "$tmp/dpkg.log" 2>&1 || { cat "$tmp/dpkg.log"; fail "dpkg -r"; }
while read -r f; do
  [ "$f" = "$conf" ] || [ "$f" = "$gate_conf" ] && continue
  [ ! -e "$f" ] && [ ! -L "$f" ] || fail "$f is still there after dpkg -r"
done < "$tmp/files"
for d in /usr/share/guardian /usr/share/doc/guardian /run/guardian; do [ ! -e "$d" ] || fail "$d remains"; done
[ "$enabled" = 0 ] || [ ! -L "$wants" ] || fail "$wants remains"
[ "$(sha256sum "$bank"; stat -c '%i %Y %U:%G %a %s' "$bank")" = "$before" ] || fail "dpkg -r touched $bank"
echo "left: $(find /var/lib/guardian /etc/guardian | tr '\n' ' ')"

step "dpkg -P: nothing remains"
dpkg -P "$pkg" > "$tmp/dpkg.log" 2>&1 || { cat "$tmp/dpkg.log"; fail "dpkg -P"; }
for f in "${dirs[@]}" "$wants" $(cat "$tmp/files"); do
  [ ! -e "$f" ] && [ ! -L "$f" ] || fail "$f is still there after dpkg -P"
done
# iceoryx2 keeps a small global segment per prefix after its last node exits; it belongs to
# the test's processes, not to the package (the trap removes it).
if ls /dev/shm/"$prefix"* >/dev/null 2>&1; then
  echo "iceoryx2 shared memory of the test's processes (removed on exit): $(cd /dev/shm && ls -d "$prefix"* | tr '\n' ' ')"
fi
dpkg-query -W -f='${db:Status-Status}' "$pkg" 2>/dev/null | grep -qv '^not-installed$' && fail "dpkg still knows $pkg"
echo "system user $user kept by the package, as Debian does (this test removes it if it made it)"

echo "test-deb: ok ($((SECONDS - start)) s)"
