#!/usr/bin/env bash
# The README's test command: installs what the test suite needs (packaging/deps.sh test:
# only missing Debian packages), checks that the Omniglot data is beside the checkout, then
# runs the whole Rust suite (extra arguments go to cargo test). `.ci/run` calls this.
set -euo pipefail
cd "$(dirname "$0")/.."
bash packaging/deps.sh test
test -d ../shared/omniglot/strokes || {
  echo "../shared/omniglot/strokes is missing: the tests read the Omniglot strokes beside the checkout" >&2
  exit 1
}
exec cargo test --workspace "$@"
