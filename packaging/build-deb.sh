#!/usr/bin/env bash
# Builds the Debian package `guardian` (README "Install on a robot PC"): builds guardiand and
# guardianctl with cargo, then packages them with cargo-deb (metadata: [package.metadata.deb]
# in daemon/Cargo.toml; maintainer scripts: packaging/debian/). Prints the .deb's path last.
# Usage: packaging/build-deb.sh [--profile PROFILE] [--no-build]
#   --profile PROFILE  cargo profile to build and package (default: release)
#   --no-build         package the binaries already built in target/<profile dir>/
set -euo pipefail
cd "$(dirname "$0")/.."

# The cargo packages that build the two binaries.
DAEMON_PACKAGE=guardian-daemon
CTL_PACKAGE=guardian-ctl
GATE_PACKAGE=guardian-gate
CARGO_DEB_VERSION=3.8.0

profile=release
build=1
while [ $# -gt 0 ]; do
  case "$1" in
    --profile) profile=${2:?--profile needs a value}; shift 2 ;;
    --no-build) build=0; shift ;;
    *) echo "usage: $0 [--profile PROFILE] [--no-build]" >&2; exit 2 ;;
  esac
done
case "$profile" in
  dev | test) dir=debug ;;
  bench) dir=release ;;
  *) dir=$profile ;;
esac
target=${CARGO_TARGET_DIR:-target}

command -v cargo-deb >/dev/null || {
  echo "cargo-deb is missing: cargo install cargo-deb --version $CARGO_DEB_VERSION --locked" >&2
  exit 1
}
if [ "$build" = 1 ]; then
  # Both binaries in one build with fleet membership on (docs/fleet.md), the same command the
  # test harness uses, so a tested dev build is reused as it is.
  cargo build --locked --profile "$profile" -p "$DAEMON_PACKAGE" -p "$CTL_PACKAGE" --bins \
    --features "$DAEMON_PACKAGE/fleet"
  cargo build --locked --profile "$profile" -p "$GATE_PACKAGE" --bins
fi
for b in guardiand guardianctl guardian-gate; do
  test -x "$target/$dir/$b" || { echo "$target/$dir/$b is missing; build it first" >&2; exit 1; }
done
mkdir -p "$target/debian"
# cargo-deb 3.8 warns that `--profile dev` will become an error in a later release; CI packages
# its dev build only to test the package's files and scripts, and the version is pinned.
# --strip: the release profile keeps line tables (debug = "line-tables-only"), which would make
# guardiand 67 MB instead of 8 MB; cargo-deb's --dbgsym would put them in a .ddeb instead.
cargo deb -p "$DAEMON_PACKAGE" --no-build --strip --profile "$profile" --output "$target/debian/"
