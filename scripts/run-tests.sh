#!/bin/sh
# Every test on a fresh Debian 12 machine: installs the packages, builds, and
# runs ctest (unit, integration, e2e, and a smoke run of the benchmarks).
set -eu
cd "$(dirname "$0")/.."
scripts/install-deps.sh
scripts/build.sh
# Clang's thread-safety analysis (ABSL_GUARDED_BY) over the library and the
# coordinator; GCC builds, clang only checks (about 35 s).
/usr/bin/python3 tests/static/thread_safety_check.py --build-dir "${BUILD_DIR:-build}"
ctest --test-dir "${BUILD_DIR:-build}" --output-on-failure -j 2
