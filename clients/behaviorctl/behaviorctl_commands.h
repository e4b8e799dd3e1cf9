#pragma once

// behaviorctl's commands: a client of one behavior system (the generic
// behaviorlib.v1.BehaviorSystem service, --target) or of the coordinator
// (behaviorlib.v1.Coordinator, --coordinator), which routes by robot and
// behavior. main() parses the command line into CtlOptions and runs one.
// The listing commands (list, systems, status, mission list, belief list)
// print an aligned table on stdout, -o wide a wider one; the others, and
// every command with -o json, print one JSON object per line (-o yaml:
// YAML documents). Messages and errors go to stderr.

#include <cstdint>
#include <string>
#include <vector>

namespace behaviorlib::behaviorctl {

struct CtlOptions {
  /// A behavior system's address; exactly one of target and coordinator.
  std::string target;
  std::string coordinator;
  /// --robot: the robot (through the coordinator); a filter for list,
  /// systems, watch.
  std::string robot;
  /// --behavior: watch only this behavior's events (coordinator).
  std::string behavior_filter;
  std::string request_id;
  std::string incarnation;
  /// watch: stop after this behavior's finished event.
  std::string until_finished;
  uint64_t since_seq = 0;
  /// watch: give up after this many seconds; health: its deadline (0: 3 s).
  double timeout_s = 0;
  bool dry_run = false;
  bool skip_plan = false;
  bool detach = false;
  bool confirm = false;
  std::string mission_id;
  /// record/replay: the data channel (broker) address.
  std::string channel;
  /// record: vehicle topics under robots/{id}/, comma-separated (empty: the
  /// default set); --duration-s: stop after this long (0: at SIGINT/SIGTERM).
  std::string topics;
  double duration_s = 0;
  /// replay: 1 as recorded, 0 as fast as the broker takes it; only MCAP
  /// topics with this prefix.
  double speed = 1;
  std::string topic_prefix;
  /// -o: table, wide, json or yaml (behaviorctl_output.h); empty: a table
  /// for the listing commands, JSON for the others.
  std::string output;
  /// The command and its arguments ("activate", "WAIT", "{...}").
  std::vector<std::string> args;
};

/// Runs the command; the process's exit code: 0 done, 1 the call failed (or
/// a mission did not succeed, or a health check found the server not
/// serving), 2 a usage error.
int runCtl(const CtlOptions& options);

/// The flight recorder's commands (behaviorctl_recorder.cc).
int runRecord(const CtlOptions& options);
int runReplay(const CtlOptions& options);

}  // namespace behaviorlib::behaviorctl
