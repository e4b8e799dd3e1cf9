#!/bin/sh
# A long libFuzzer run measured in CPU time, not wall time (docs/fuzzing.md).
#
#   scripts/fuzz-long.sh TARGET [CPU_SECONDS]      default 3600: a core-hour
#
# libFuzzer's -max_total_time counts wall time, so on a busy machine an
# "hour" may be a few minutes of fuzzing. This runs TARGET (built in
# build-asan, or $ASAN_BUILD_DIR) at the lowest priority, reads its CPU time
# (user + system) from /proc every 5 s, and interrupts it with SIGINT once it
# has used CPU_SECONDS; libFuzzer then prints its final statistics and exits.
# A crash, leak, timeout or out-of-memory ends the run earlier and is reported.
#
# Its corpus is kept in <tree>/fuzz-long/TARGET between runs; the repository's
# corpus is only read. The log is <tree>/fuzz-artifacts/TARGET.long.log, and the
# last line printed is a summary for docs/fuzzing.md's table.
set -eu
cd "$(dirname "$0")/.."
REPO="$(pwd)"
TREE="${ASAN_BUILD_DIR:-build-asan}"

target="${1:-}"
budget="${2:-3600}"
case "$target" in
  fuzz_*) ;;
  *) echo "usage: $0 fuzz_TARGET [CPU_SECONDS]" >&2; exit 2 ;;
esac
case "$budget" in
  ''|*[!0-9]*) echo "CPU_SECONDS must be a whole number" >&2; exit 2 ;;
esac
binary="$TREE/tests/fuzz/$target"
if [ ! -x "$binary" ]; then
  echo "$binary is not built: run scripts/sanitizer-tests.sh asan first" >&2
  exit 2
fi

cd "$TREE"
mkdir -p "fuzz-long/$target" fuzz-artifacts
log="fuzz-artifacts/$target.long.log"
ticks="$(getconf CLK_TCK)"
started="$(date -u +%Y-%m-%dT%H:%M:%SZ)"
start_s="$(date +%s)"

# In a session of its own, whose autogroup gets the lowest weight: with
# autogroup scheduling (Linux's default), nice counts only within a session,
# so a niced fuzzer would still take a core from a build started elsewhere.
pidfile="fuzz-artifacts/$target.pid"
rm -f "$pidfile"
setsid sh -c 'echo $$ > "$0"; exec nice -n 19 "$@"' "$pidfile" \
  "tests/fuzz/$target" -rss_limit_mb=2048 -timeout=60 -print_final_stats=1 \
  -artifact_prefix="fuzz-artifacts/$target-" "fuzz-long/$target" "$REPO/tests/fuzz/corpus/$target" \
  > "$log" 2>&1 < /dev/null &
tries=0
while [ ! -s "$pidfile" ] && [ "$tries" -lt 100 ]; do
  sleep 0.1
  tries=$((tries + 1))
done
pid="$(cat "$pidfile")"
echo 19 > "/proc/$pid/autogroup" 2>/dev/null || true
# Stopped itself (Ctrl-C, a timeout): the fuzzer, in its own session, is
# interrupted too.
trap 'kill -INT "$pid" 2>/dev/null; exit 130' INT TERM HUP

cpu_s=0
while kill -0 "$pid" 2>/dev/null; do
  # Fields 14 and 15 of /proc/PID/stat are utime and stime in clock ticks; the
  # command name (field 2) has no spaces for our targets.
  if stat_line="$(cat "/proc/$pid/stat" 2>/dev/null)"; then
    cpu_s="$(echo "$stat_line" | awk -v t="$ticks" '{ printf "%d", ($14 + $15) / t }')"
    if [ "$cpu_s" -ge "$budget" ]; then
      kill -INT "$pid" 2>/dev/null || true
      break
    fi
  fi
  sleep 5
done
# Not our child (setsid): wait until it is gone.
while kill -0 "$pid" 2>/dev/null; do sleep 1; done
rm -f "$pidfile"
wall_s=$(($(date +%s) - start_s))

first_cov="$(grep -m1 -o 'INITED cov: [0-9]*' "$log" | grep -o '[0-9]*$' || true)"
last_cov="$(grep -o 'cov: [0-9]*' "$log" | tail -n 1 | grep -o '[0-9]*$' || true)"
runs="$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' || true)"
rss="$(grep -o 'stat::peak_rss_mb: *[0-9]*' "$log" | grep -o '[0-9]*$' || true)"
corpus="$(find "fuzz-long/$target" -type f | wc -l)"
if grep -q 'libFuzzer: run interrupted' "$log"; then
  outcome="0 findings"
else
  outcome="ENDED EARLY: see $TREE/$log and $TREE/fuzz-artifacts/"
fi
echo "$target | started $started | wall ${wall_s} s | CPU ${cpu_s} s | ${runs:-?} executions |" \
  "cov ${first_cov:-?} -> ${last_cov:-?} | corpus $corpus files | peak RSS ${rss:-?} MB | $outcome"
case "$outcome" in
  "0 findings") exit 0 ;;
  *) exit 1 ;;
esac
