#!/bin/sh
# Installs every Debian 12 package behaviorlib needs to build, test and run.
# Used by .ci/run, the README and deploy/compose/Dockerfile.
#   scripts/install-deps.sh          build + runtime + test packages
#   scripts/install-deps.sh --build  build + runtime packages only (Docker build stage)
set -eu

BUILD_PACKAGES="g++ cmake ninja-build pkg-config libgtest-dev libgmock-dev libbenchmark-dev \
  libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler libeigen3-dev \
  libompl-dev libboost-serialization-dev libboost-filesystem-dev libboost-system-dev \
  liboctomap-dev libopencv-dev libopencv-contrib-dev prometheus-cpp-dev libyaml-cpp-dev grpc-proto"
TEST_PACKAGES="python3 python3-grpcio python3-protobuf prometheus docker-compose procps"

packages="$BUILD_PACKAGES"
if [ "${1:-}" != "--build" ]; then
  packages="$packages $TEST_PACKAGES"
fi

SUDO=""
if [ "$(id -u)" != "0" ]; then
  SUDO="sudo"
fi

export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update
# --no-install-recommends: with recommends, docker-compose pulls in a whole Docker engine.
# shellcheck disable=SC2086
$SUDO apt-get install -y --no-install-recommends $packages
