#!/bin/sh
# Sanitizer builds and their tests (decision 25, docs/sanitizers.md).
#
#   scripts/sanitizer-tests.sh asan   ASan+UBSan (clang-14, -O1): unit and
#                                     integration tests, plus a smoke run of every
#                                     libFuzzer target (same tree) -> build-asan/
#   scripts/sanitizer-tests.sh tsan   TSan (clang-14, -O1): the library, channel
#                                     and coordinator tests, and the in-process
#                                     servers' integration tests -> build-tsan/
#
# Only the subsets below are built, so both fit in CI beside the Release build
# (docs/sanitizers.md says how they were chosen). Every report, also one from
# a server process that a test started, is written under <tree>/sanitizer-logs
# and fails the run.
set -eu
cd "$(dirname "$0")/.."
REPO="$(pwd)"

mode="${1:-}"
case "$mode" in
  asan)
    TREE="${ASAN_BUILD_DIR:-build-asan}"
    SANITIZE="address,undefined"
    # 10 s of fuzzing per target beyond its seeds (docs/fuzzing.md for long runs).
    EXTRA="-DBEHAVIORLIB_FUZZ=ON -DBEHAVIORLIB_FUZZ_SMOKE_S=10"
    # Unit tests: the library, server kit, channel, coordinator and
    # simulator, whose code every program runs.
    UNIT="parameters_test event_log_test behavior_execution_manager_test process_supervisor_test
      wait_behavior_test worker_delivery_test channel_topic_test sim_clock_test shm_ring_test
      sim_world_test sim_sensor_config_test sim_sensors_test sim_fault_injector_test catalog_test
      missions_test coordinator_core_test flags_test input_guard_test access_policy_test
      pagination_test audit_log_test error_details_test console_feed_test recorder_test"
    # Integration tests: the servers' own tests, in-process and as real
    # processes (coordinator, broker, simulator, a behavior system). The
    # other behavior systems' code is in their Release tests.
    INTEGRATION="reflection_service_test channel_broker_test broker_in_process_test
      behavior_system_test behavior_system_in_process_test simulator_in_process_test
      simulator_service_test coordinator_in_process_test coordinator_beliefs_test
      coordinator_hardening_test authorizer_in_process_test"
    # Tests that are scripts or second runs (not build targets) driving the
    # programs above: the contract suite against contract_behaviors (its
    # watchdog, exception and time-out paths).
    SCRIPTS="console_gateway_test behavior_system_contract_test"
    PROGRAMS="coordinator channel_broker simulator basic_quadrotor_behaviors console behaviorctl
      contract_behaviors"
    FUZZERS="fuzz_mission_file fuzz_world_file fuzz_sensor_config fuzz_catalog
      fuzz_systems_config fuzz_parameters_struct fuzz_parameters_json fuzz_journal
      fuzz_channel_sample fuzz_mcap"
    ;;
  tsan)
    TREE="${TSAN_BUILD_DIR:-build-tsan}"
    SANITIZE="thread"
    EXTRA=""
    UNIT="parameters_test event_log_test behavior_execution_manager_test process_supervisor_test
      wait_behavior_test worker_delivery_test channel_topic_test sim_clock_test shm_ring_test
      catalog_test missions_test coordinator_core_test flags_test input_guard_test
      access_policy_test pagination_test audit_log_test error_details_test console_feed_test
      recorder_test setpoint_barrier_test"
    # The integration tests whose servers run in the test's process. Our
    # reactors and client completions tell TSan the order gRPC keeps
    # (reactor_order.h); a server run as its own program would need its own
    # TSan build, which CI has no time for.
    INTEGRATION="reflection_service_test broker_in_process_test behavior_system_in_process_test
      simulator_in_process_test coordinator_in_process_test authorizer_in_process_test"
    PROGRAMS=""
    SCRIPTS=""
    FUZZERS=""
    ;;
  *)
    echo "usage: $0 asan|tsan" >&2
    exit 2
    ;;
esac

# -O1 with line tables: stack traces name the line, the build stays fast.
# shellcheck disable=SC2086
cmake -S . -B "$TREE" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DCMAKE_C_COMPILER=clang-14 -DCMAKE_CXX_COMPILER=clang++-14 \
  "-DCMAKE_CXX_FLAGS_RELWITHDEBINFO=-O1 -gline-tables-only" \
  "-DCMAKE_C_FLAGS_RELWITHDEBINFO=-O1 -gline-tables-only" \
  -DBEHAVIORLIB_SANITIZE="$SANITIZE" $EXTRA >/dev/null
# shellcheck disable=SC2086
cmake --build "$TREE" -j "$(nproc)" --target $UNIT $INTEGRATION $PROGRAMS $FUZZERS

LOGS="$REPO/$TREE/sanitizer-logs"
rm -rf "$LOGS"
mkdir -p "$LOGS"
SUPP="$REPO/tests/sanitizers"
if [ "$mode" = asan ]; then
  export ASAN_OPTIONS="log_path=$LOGS/asan:detect_leaks=1:strict_init_order=1:detect_stack_use_after_return=1"
  export LSAN_OPTIONS="suppressions=$SUPP/lsan.supp:print_suppressions=0"
  export UBSAN_OPTIONS="log_path=$LOGS/ubsan:print_stacktrace=1:halt_on_error=1"
else
  export TSAN_OPTIONS="log_path=$LOGS/tsan:suppressions=$SUPP/tsan.supp:print_suppressions=0:second_deadlock_stack=1"
fi

names=""
for t in $UNIT $INTEGRATION $SCRIPTS; do names="${names:+$names|}$t"; done
for t in $FUZZERS; do names="${names:+$names|}${t}_smoke"; done
status=0
ctest --test-dir "$TREE" --output-on-failure -j 2 -R "^($names)\$" || status=$?

# A report from a server process does not always fail the test that started
# it (the server may be stopped with SIGKILL right after): every report does.
reports=$(find "$LOGS" -type f | sort)
if [ -n "$reports" ]; then
  for r in $reports; do
    echo "==== $r"
    cat "$r"
  done
  echo "sanitizer-tests ($mode): $(echo "$reports" | wc -l) report(s), see above" >&2
  status=1
fi
if [ "$status" -ne 0 ]; then
  echo "sanitizer-tests ($mode): FAILED" >&2
  exit "$status"
fi
echo "sanitizer-tests ($mode): clean"
