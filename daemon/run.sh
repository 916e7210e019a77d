#!/usr/bin/env bash
# The README's run command: installs the build's Debian packages if missing
# (packaging/deps.sh build), then runs guardiand on the shipped default model and bank
# (release build; extra arguments go to guardiand, e.g. --config FILE).
set -euo pipefail
cd "$(dirname "$0")/.."
bash packaging/deps.sh build
exec cargo run --release -p guardian-daemon --bin guardiand -- "$@"
