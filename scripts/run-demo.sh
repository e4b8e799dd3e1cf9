#!/bin/sh
# The main job on a fresh Debian 12 machine: installs the packages it needs
# (not the test tools), builds what the demo runs (the `demo` target: the
# tests and the other systems are built by scripts/run-tests.sh), and runs
# the whole stack on loopback (no Docker) with the demo mission end to end.
# Extra arguments go to the launcher (e.g. --time-scale 2, --run-dir DIR);
# see deploy/local/launch.py --help.
set -eu
cd "$(dirname "$0")/.."
scripts/install-deps.sh --demo
scripts/build.sh demo
exec /usr/bin/python3 deploy/local/launch.py --build-dir "${BUILD_DIR:-build}" --demo "$@"
