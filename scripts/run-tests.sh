#!/bin/sh
# Every test on a fresh Debian 12 machine: installs the packages, builds, and
# runs ctest (unit, integration, e2e, and a smoke run of the benchmarks).
set -eu
cd "$(dirname "$0")/.."
scripts/install-deps.sh
scripts/build.sh
ctest --test-dir "${BUILD_DIR:-build}" --output-on-failure -j 2
