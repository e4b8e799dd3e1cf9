#!/bin/sh
# The compose deployment under test: builds the image as the README says,
# brings the documented stack up in containers with docker-compose and runs
# the tests labelled `container` against it (tests/container). Called by
# scripts/run-tests.sh after the other tests; runs alone too:
#
#   scripts/container-tests.sh
#   scripts/container-tests.sh --run CMD ARG...   # CMD instead, with the engine
#
# The engine: the one that answers at DOCKER_HOST or the default socket,
# used as it is and left running with its images. Otherwise this script
# starts Debian's dockerd with a data root of its own under
# BEHAVIORLIB_CACHE_DIR (default /var/cache/behaviorlib), so that the base
# images, the image layers and the build caches outlive the run, and stops
# that daemon at the end. A machine where no engine can run skips the stage
# with a message saying why (exit 0); BEHAVIORLIB_REQUIRE_CONTAINERS=1 makes
# that an error.
#
# Without a registry: the Debian 12 base images (debian:12, debian:12-slim)
# are made from Debian's packages with mmdebstrap and imported, once per key
# (the release, the variant and the archive lines), and Prometheus's image
# is built from Debian's package (deploy/compose/docker-compose.offline.yml).
# Grafana is not packaged by Debian: it is left out unless its image is
# present.
set -eu
cd "$(dirname "$0")/.."
REPO="$(pwd)"
BUILD_DIR="${BUILD_DIR:-build}"
CACHE_DIR="${BEHAVIORLIB_CACHE_DIR:-/var/cache/behaviorlib}"
# Debian's client matches Debian's engine (20.10); a newer client elsewhere on
# PATH may lack the BuildKit plugin that its `docker build` needs.
PATH="/usr/sbin:/usr/bin:/sbin:/bin:$PATH"
export PATH

say() { printf 'container-tests: %s\n' "$*"; }
skip() {
  say "SKIPPED: $*"
  if [ "${BEHAVIORLIB_REQUIRE_CONTAINERS:-0}" = "1" ]; then exit 1; fi
  exit 0
}
started_at=$(date +%s)
elapsed() { echo $(($(date +%s) - started_at)); }

SUDO=""
if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi

# --- packages ---------------------------------------------------------------
missing=""
command -v dockerd > /dev/null 2>&1 || missing="$missing docker.io"
command -v docker-compose > /dev/null 2>&1 || missing="$missing docker-compose"
command -v mmdebstrap > /dev/null 2>&1 || missing="$missing mmdebstrap"
if [ -n "$missing" ]; then
  say "installing$missing"
  # shellcheck disable=SC2086
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y --no-install-recommends $missing \
    > /dev/null || skip "could not install$missing"
fi

# --- the engine ---------------------------------------------------------------
own_daemon_pid=""
stop_daemon() {
  if [ -n "$own_daemon_pid" ]; then
    say "stopping the dockerd this script started (pid $own_daemon_pid)"
    $SUDO kill "$own_daemon_pid" 2> /dev/null || true
    i=0
    while $SUDO kill -0 "$own_daemon_pid" 2> /dev/null && [ $i -lt 60 ]; do
      sleep 0.5
      i=$((i + 1))
    done
  fi
}
trap stop_daemon EXIT
trap 'exit 130' INT TERM

if [ -z "${DOCKER_HOST:-}" ] && ! docker version > /dev/null 2>&1; then
  run_dir=/run/behaviorlib-docker
  $SUDO mkdir -p "$CACHE_DIR/docker" "$run_dir"
  DOCKER_HOST="unix://$run_dir/docker.sock"
  export DOCKER_HOST
  if docker version > /dev/null 2>&1; then
    say "using the dockerd a previous run left at $DOCKER_HOST"
  else
    say "starting dockerd (data root $CACHE_DIR/docker, log $run_dir/dockerd.log)"
    $SUDO dockerd --data-root "$CACHE_DIR/docker" --exec-root "$run_dir/exec" \
      --pidfile "$run_dir/dockerd.pid" -H "$DOCKER_HOST" \
      --exec-opt native.cgroupdriver=cgroupfs --storage-driver overlay2 \
      > "$run_dir/dockerd.log" 2>&1 &
    own_daemon_pid=$!
    i=0
    until docker version > /dev/null 2>&1; do
      if ! kill -0 "$own_daemon_pid" 2> /dev/null || [ $i -ge 120 ]; then
        tail -n 5 "$run_dir/dockerd.log" >&2 || true
        stop_daemon
        own_daemon_pid=""
        skip "no Docker engine can run on this machine (dockerd exited, or did not" \
          "answer within 60 s; its log's end is above)"
      fi
      sleep 0.5
      i=$((i + 1))
    done
  fi
else
  say "using the engine at ${DOCKER_HOST:-the default socket}"
fi
docker version --format 'container-tests: engine {{.Server.Version}}, client {{.Client.Version}}'

# --- base images ----------------------------------------------------------------
# The archive lines the base images are made from, and their cache key.
DEBIAN_RELEASE=bookworm
DEBIAN_SOURCES="deb http://deb.debian.org/debian bookworm main
deb http://deb.debian.org/debian bookworm-updates main
deb http://deb.debian.org/debian-security bookworm-security main"
base_key="$(printf '%s\nminbase\n%s\n' "$DEBIAN_RELEASE" "$DEBIAN_SOURCES" \
  | sha256sum | cut -c1-16)"
label_of() {
  if docker image inspect "$1" > /dev/null 2>&1; then
    docker image inspect --format '{{index .Config.Labels "org.behaviorlib.base-key"}}' "$1"
  else
    echo absent
  fi
}
for tag in debian:12 debian:12-slim; do
  key="$(label_of "$tag")"
  case "$key" in
    "$base_key")
      say "$tag: made from Debian's packages, key $base_key (cached)"
      continue
      ;;
    absent | [0-9a-f]*[0-9a-f]) ;; # none, or one of ours of another key
    *)
      say "$tag: present in the engine (not made here), used as it is"
      continue
      ;;
  esac
  tar="$CACHE_DIR/debian-$DEBIAN_RELEASE-minbase-$base_key.tar"
  if [ ! -f "$tar" ]; then
    say "making $tag from Debian's packages (mmdebstrap, key $base_key)"
    $SUDO mkdir -p "$CACHE_DIR"
    # (mmdebstrap tells the output's format by its name: .tar)
    part="${tar%.tar}.part.tar"
    printf '%s\n' "$DEBIAN_SOURCES" | $SUDO mmdebstrap --quiet --variant=minbase \
      "$DEBIAN_RELEASE" "$part" - && $SUDO mv "$part" "$tar"
  fi
  docker import --change "LABEL org.behaviorlib.base-key=$base_key" \
    --change 'CMD ["bash"]' "$tar" "$tag" > /dev/null
  say "$tag: imported (key $base_key)"
done

# --- or a command of the caller's, with this engine -------------------------------
# `scripts/container-tests.sh --run CMD ARG...` runs CMD with DOCKER_HOST set to
# the engine above and the base images made, instead of the image build and the
# tests (tests/bench/stack/first_run_bench.py uses it); its exit code is CMD's.
if [ "${1:-}" = "--run" ]; then
  shift
  say "running $* with the engine"
  rc=0
  "$@" || rc=$?
  exit "$rc"
fi

# --- the image, as the README builds it -------------------------------------------
say "building behaviorlib:latest ($(elapsed) s so far)"
build_started=$(date +%s)
DOCKER_BUILDKIT=1 docker build -f deploy/compose/Dockerfile -t behaviorlib:latest . \
  > "$CACHE_DIR/image-build.log" 2>&1 || {
  tail -n 40 "$CACHE_DIR/image-build.log" >&2
  say "the image did not build (log: $CACHE_DIR/image-build.log)"
  exit 1
}
size="$(docker image inspect --format '{{.Size}}' behaviorlib:latest)"
say "behaviorlib:latest built in $(($(date +%s) - build_started)) s, $((size / 1000000)) MB"

# --- the tests -------------------------------------------------------------------
if [ ! -f "$BUILD_DIR/CTestTestfile.cmake" ]; then
  say "no build tree at $BUILD_DIR: building it (scripts/build.sh)"
  BUILD_DIR="$BUILD_DIR" scripts/build.sh
fi
BEHAVIORLIB_CACHE_DIR="$CACHE_DIR" DOCKER_HOST="${DOCKER_HOST:-}" \
  ctest --test-dir "$BUILD_DIR" -L container --output-on-failure
say "done in $(elapsed) s"
