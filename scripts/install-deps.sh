#!/bin/sh
# Installs every Debian 12 package behaviorlib needs to build, test and run.
# Used by .ci/run, the README and deploy/compose/Dockerfile.
#   scripts/install-deps.sh          build + runtime + test packages
#   scripts/install-deps.sh --build  build + runtime packages only (Docker build stage)
#   scripts/install-deps.sh --demo   build packages and what the launcher and its report
#                                    use (scripts/run-demo.sh): no test tools
#   scripts/install-deps.sh --runtime  the shared libraries the binaries load, nothing else
#                                      (Docker runtime stage; tests/deploy checks the list)
set -eu

BUILD_PACKAGES="g++ cmake ninja-build pkg-config libgtest-dev libgmock-dev libbenchmark-dev \
  libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev libprotoc-dev protobuf-compiler libeigen3-dev \
  golang-github-gogo-googleapis-dev \
  libompl-dev libboost-serialization-dev libboost-filesystem-dev libboost-system-dev \
  liboctomap-dev libopencv-dev libopencv-contrib-dev prometheus-cpp-dev libyaml-cpp-dev grpc-proto \
  libssl-dev libcpp-httplib-dev zlib1g-dev libturbojpeg0-dev libpng-dev ccache libnats-dev"
# What the built binaries load (each package pulls in its own dependencies), for
# a machine that only runs them (Docker runtime stage). When a binary comes to
# need another library, tests/deploy/runtime_packages_test.py names the package
# to add here. OpenCV's libraries are not installed from packages in the image
# but copied from the build stage (deploy/compose/copy-libraries.sh, decision
# 38): Debian's libopencv-core406 alone pulls in Mesa and LLVM (220 MB). What
# the copied libraries load is here: libtbb12, liblapack3, libblas3, libx11-6.
RUNTIME_PACKAGES="libstdc++6 libgcc-s1 zlib1g libssl3 libgrpc++1.51 libgrpc29 libprotobuf32 \
  libabsl20220623 libprometheus-cpp-core1.0 libprometheus-cpp-pull1.0 libyaml-cpp0.7 \
  liboctomap1.9 libompl16 libcpp-httplib0.11 libturbojpeg0 libpng16-16 \
  libtbb12 liblapack3 libblas3 libx11-6 libnats3.4 nats-server"
TEST_PACKAGES="python3 python3-grpcio python3-protobuf python3-numpy python3-prometheus-client python3-yaml python3-venv python3-setuptools \
  python3-wheel python3-websocket python3-pytest python3-matplotlib python3-pil prometheus docker-compose procps openssl \
  clang-14 libclang-rt-14-dev libfuzzer-14-dev llvm-14 chromium \
  nats-server cyclonedds-dev cyclonedds-tools iproute2 iptables stress-ng"

# The launcher (deploy/local/launch.py) and its report: gRPC reflection from
# Python, the mission files, the plots, /proc readers.
DEMO_PACKAGES="python3 python3-grpcio python3-protobuf python3-yaml python3-matplotlib procps \
  python3-venv python3-setuptools python3-wheel"

# npm (with Node.js) installs the pinned tools of tests/api (buf) and
# tests/deploy (@grafana/schema, TypeScript) into the build tree. Debian's npm
# is left out where a Node.js with npm is already installed, which it would
# conflict with.
NPM_PACKAGE="npm"
if command -v npm > /dev/null 2>&1; then
  NPM_PACKAGE=""
fi

case "${1:-}" in
  "") packages="$BUILD_PACKAGES $TEST_PACKAGES $NPM_PACKAGE" ;;
  --build) packages="$BUILD_PACKAGES" ;;
  --demo) packages="$BUILD_PACKAGES $DEMO_PACKAGES" ;;
  --runtime) packages="$RUNTIME_PACKAGES" ;;
  *)
    echo "usage: $0 [--build | --demo | --runtime]" >&2
    exit 2
    ;;
esac

SUDO=""
if [ "$(id -u)" != "0" ]; then
  SUDO="sudo"
fi

export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update
# --no-install-recommends: with recommends, docker-compose pulls in a whole Docker engine.
# shellcheck disable=SC2086
$SUDO apt-get install -y --no-install-recommends $packages
