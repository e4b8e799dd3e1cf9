#!/bin/sh
# Every test on a fresh Debian 12 machine: installs the packages, builds, and
# runs ctest (unit, integration, e2e, and a smoke run of the benchmarks), then
# the ASan+UBSan (with the fuzz targets) and TSan builds of their subsets, and
# the compose deployment in containers (scripts/container-tests.sh).
set -eu
cd "$(dirname "$0")/.."
scripts/install-deps.sh
scripts/build.sh
# Clang's thread-safety analysis (ABSL_GUARDED_BY) over the library and the
# coordinator; GCC builds, clang only checks (about 2.5 minutes on 2 cores).
/usr/bin/python3 tests/static/thread_safety_check.py --build-dir "${BUILD_DIR:-build}"
# The label container runs last, alone (scripts/container-tests.sh).
ctest --test-dir "${BUILD_DIR:-build}" --output-on-failure -j 2 -LE container
# Sanitizer builds of chosen subsets, and the fuzz targets' smoke runs
# (docs/sanitizers.md): each builds its own tree with clang-14.
scripts/sanitizer-tests.sh asan
scripts/sanitizer-tests.sh tsan
# The compose deployment: the image built as the README says, the stack run
# in containers and flown (skipped, saying why, where no engine can run).
scripts/container-tests.sh
