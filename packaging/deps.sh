#!/usr/bin/env bash
# Installs the Debian packages the project needs, only those missing, for one purpose:
#   build  building the workspace: iceoryx2's bindings (clang, libclang-dev), the lab's and
#          the examples' plots (pkg-config, fontconfig, freetype, DejaVu fonts)
#   test   build + what the test suite runs for real: systemd's tools (systemd-analyze),
#          util-linux, Prometheus (promtool and the server) and Chromium (tests/tests/observe.rs)
#   ci     test + Python 3 with venv (python/ci.sh) + iproute2 (ip netns and ss, the gate's
#          gate/tests/netns/run.sh) + fastdds
#   fastdds  the Fast DDS interop test (gate/tests/fastdds/run.sh): Fast DDS 2.9 and its
#          type generator (Java), g++
# Needs root, or sudo. The Rust toolchain itself comes from rustup.
set -euo pipefail
what="${1:-test}"
build=(pkg-config libfontconfig1-dev libfreetype-dev fonts-dejavu-core libclang-dev clang)
test=(systemd util-linux prometheus chromium)
ci=(python3 python3-venv iproute2)
fastdds=(libfastrtps-dev fastddsgen g++)
case "$what" in
  build) pkgs=("${build[@]}") ;;
  test) pkgs=("${build[@]}" "${test[@]}") ;;
  ci) pkgs=("${build[@]}" "${test[@]}" "${ci[@]}" "${fastdds[@]}") ;;
  fastdds) pkgs=("${fastdds[@]}") ;;
  *) echo "usage: $0 build|test|ci|fastdds" >&2; exit 2 ;;
esac
missing=()
for p in "${pkgs[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
[ "${#missing[@]}" -eq 0 ] && exit 0
echo "installing Debian packages: ${missing[*]}" >&2
as_root=()
[ "$(id -u)" -eq 0 ] || as_root=(sudo)
"${as_root[@]}" apt-get update -qq
DEBIAN_FRONTEND=noninteractive "${as_root[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}"
