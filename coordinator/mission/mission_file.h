#pragma once

// Mission files (YAML): what a mission activates, in which order, and what
// each termination cause leads to. The grammar, with an example a construct
// (each run by coordinator_plans_missions_test), is docs/missions.md.
//
//   name: inspect_and_land
//   robot: drone1                       # the start request may name another
//   recurrent:                          # active during the whole mission
//     - behavior: SELF_LOCALIZE_WITH_GROUND_TRUTH
//   geofence: {min_m: [-10, -10, 0], max_m: [10, 10, 5]}   # optional
//   safety:                             # run when the mission aborts
//     - behavior: LAND
//   steps:
//     - name: take_off
//       behavior: TAKE_OFF
//       parameters: {altitude_m: 1.5}
//       on:
//         TIME_OUT: {retry: 2}          # then abort (or: {retry: 2, then: continue})
//         WRONG_PROGRESS: {fallback: [{behavior: LAND}]}
//         REFUSED: continue             # the activation itself was refused
//         otherwise: abort              # every cause not listed (GOAL_ACHIEVED continues)
//     - name: follow
//       if: {belief: drone1/path, exists: true}       # or {belief: k, equals: v}
//       behavior: FOLLOW_PATH
//       parameters: {path: "${belief.drone1/path}"}   # the belief's value
//       remember: {followed: true}      # written to belief memory on GOAL_ACHIEVED
//
// Actions: continue, abort, {retry: N[, then: <action>]}, {fallback: [steps]}
// (the fallback steps replace the failed step; the mission then continues).
// Causes: GOAL_ACHIEVED, TIME_OUT, WRONG_PROGRESS, SITUATION_CHANGE,
// PROCESS_FAILURE, INTERRUPTED, and REFUSED (the activation failed: plan,
// parameters, situation). A recurrent behavior that finishes during the
// mission aborts it. A step may have no behavior and only `remember`.
//
// A problem of the file's form is INVALID_ARGUMENT "<file>:<line>: <what>:
// <problem>"; checkMission() then lists every problem against the registered
// behaviors.

#include <google/protobuf/struct.pb.h>

#include <array>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "behaviorlib/v1/behavior.pb.h"

namespace behaviorlib::coordinator {

struct MissionStep;

/// What a termination cause leads to.
struct MissionAction {
  enum class Kind { kContinue, kAbort, kRetry, kFallback };
  Kind kind = Kind::kAbort;
  int retries = 0;                      ///< kRetry: extra attempts
  std::shared_ptr<MissionAction> then;  ///< kRetry: when exhausted (null: abort)
  std::vector<MissionStep> fallback;    ///< kFallback
  int line = 0;
};

/// A condition on belief memory.
struct BeliefCondition {
  std::string key;
  std::optional<bool> exists;                     ///< {exists: true|false}
  std::optional<google::protobuf::Value> equals;  ///< {equals: value}
  int line = 0;
};

/// A loop: its steps (MissionStep::body) run once an item or an iteration.
struct MissionLoop {
  enum class Kind { kForEach, kTimes, kUntil };
  Kind kind = Kind::kTimes;
  /// kForEach: the items (literal), or the belief that holds them (read
  /// when the loop starts); each is ${each.<as>} in the steps.
  google::protobuf::ListValue items;
  std::string belief;
  std::string as;
  int max_items = 0;
  /// kTimes: how many times; kUntil: at most how many (then it ends
  /// WRONG_PROGRESS), checking `until` after each iteration.
  int times = 0;
  std::optional<BeliefCondition> until;
};

/// One branch of a parallel step: a sequence of steps (a single step, a
/// call or a loop is a sequence of one).
struct MissionBranch {
  std::string name;
  std::vector<MissionStep> steps;
};

/// Branches that run at once. `all`: it ends GOAL_ACHIEVED when every branch
/// did, or with the cause of the first branch that failed (the others are
/// interrupted). `any`: it ends GOAL_ACHIEVED with the first branch that
/// did (the others are interrupted), or, when every branch failed, with the
/// cause of the last one.
struct MissionParallel {
  bool any = false;
  std::vector<MissionBranch> branches;
};

/// A synchronisation point: a step that waits until another step (by
/// name, in any branch, on any robot) ended GOAL_ACHIEVED, or until a belief
/// condition holds; TIME_OUT after `timeout_s` of the vehicles' time.
struct MissionWait {
  std::string step;
  std::optional<BeliefCondition> belief;
  double timeout_s = 0;
};

/// A condition on the vehicle, evaluated while a behavior step runs: when
/// it holds, the behavior is deactivated and the step ends with `ends`.
/// Each reads the latest sample of a topic of the step's robot; a topic whose
/// sample did not advance for `max_age_s` (the flight behaviors' staleness
/// rule) ends the step PROCESS_FAILURE.
struct VehicleCondition {
  enum class Kind {
    kBatteryBelow,  ///< FlightStatus.battery_ratio on robots/{robot}/flight_state
    kNear,          ///< the pose estimate within `radius_m` of `point_m`
  };
  Kind kind = Kind::kBatteryBelow;
  double battery_ratio = 0;
  std::array<double, 3> point_m{};
  double radius_m = 0;
  std::string ends = "SITUATION_CHANGE";  ///< a cause name
  double max_age_s = 1.0;
  int line = 0;
};

struct MissionStep {
  std::string name;  ///< empty: "step <n>"
  /// The robot it commands: its own `robot:`, else its branch's or
  /// enclosing step's; empty: the mission's robot.
  std::string robot;
  std::string behavior;  ///< empty: a call, or a step that only remembers
  /// A call of a sub-mission: its name, the `with` given, and its steps
  /// parsed with the call's parameters (${param.x} replaced).
  std::string call;
  google::protobuf::Struct with;
  std::vector<MissionStep> body;
  /// A loop over `body` (a step with a loop has no behavior and no call).
  std::optional<MissionLoop> loop;
  /// Branches that run at once (a step with them has nothing else to run).
  std::optional<MissionParallel> parallel;
  /// A wait (a step with it has nothing else to run).
  std::optional<MissionWait> wait;
  std::string file;  ///< the file the step is in (an imported one for a sub-mission's)
  google::protobuf::Struct parameters;
  std::map<std::string, int> parameter_lines;
  /// Keyed by cause name ("TIME_OUT", ..., "REFUSED") or "otherwise".
  std::map<std::string, MissionAction> on;
  std::optional<BeliefCondition> condition;
  /// Conditions on the vehicle while its behavior runs (`when:`).
  std::vector<VehicleCondition> when;
  google::protobuf::Struct remember;
  int line = 0;
  std::string path;  ///< in the document, e.g. "steps[2]" (error details)
};

/// An axis-aligned box the vehicle must stay in (world ENU, metres).
struct Geofence {
  std::array<double, 3> min_m{};
  std::array<double, 3> max_m{};
  int line = 0;
  bool contains(double x, double y, double z) const {
    return x >= min_m[0] && x <= max_m[0] && y >= min_m[1] && y <= max_m[1] && z >= min_m[2] &&
           z <= max_m[2];
  }
};

struct MissionSpec {
  std::string file;  ///< for messages
  std::string name;
  std::string description;
  std::string robot_id;
  int robot_line = 0;  ///< of `robot:`; 0 when the file has none
  /// Leaving it makes the coordinator hover the vehicle and abort the mission.
  std::optional<Geofence> geofence;
  std::vector<MissionStep> recurrent;
  std::vector<MissionStep> safety;
  std::vector<MissionStep> steps;
  /// Every robot its steps name (`robot:` of a step or a branch, recurrent
  /// and safety steps included), in file order; the mission's robot is not
  /// among them unless a step names it.
  std::vector<std::string> robots;
  /// The sub-missions it defines or imports, by name.
  std::vector<std::string> submissions;
  /// The imported files' texts, by the path the mission names them with
  /// (journaled with the mission, so that a restart parses the same).
  std::map<std::string, std::string> imports;
  int line = 1;
};

/// The robots a mission commands when started for `robot_id` (the file's
/// or the request's): `robot_id` first, then the others its steps name.
std::vector<std::string> missionRobots(const MissionSpec& mission, const std::string& robot_id);

/// Calls `visit` on every step of `steps`, and of their calls, loops,
/// parallel branches and fallbacks (depth-first, in file order).
void forEachStep(const std::vector<MissionStep>& steps,
                 const std::function<void(const MissionStep&)>& visit);

/// Reads a file that a mission imports (confined to the mission directory).
using ImportReader = std::function<absl::StatusOr<std::string>(const std::string& path)>;

/// Parses mission text; `file` names it in messages.
absl::StatusOr<MissionSpec> parseMission(const std::string& yaml, const std::string& file,
                                         const ImportReader& imports = nullptr);
/// Reads and parses a mission file.
absl::StatusOr<MissionSpec> loadMission(const std::string& path);

/// The registered description of `behavior` on `robot` (empty: the
/// mission's robot), or nullptr when no system of the robot hosts it.
using BehaviorLookup = std::function<const v1::BehaviorDescription*(const std::string& robot,
                                                                    const std::string& behavior)>;

/// One problem a check found.
struct MissionProblem {
  std::string file;
  int line = 0;             ///< 0: the whole mission
  std::string field;        ///< e.g. "steps[2].parameters.altitude_m"
  std::string description;  ///< "<file>:<line>: <what>"
};

/// What a check found: every problem in file order, at most kMaxProblems
/// (the others are counted).
struct MissionProblems {
  static constexpr std::size_t kMaxProblems = 50;
  std::vector<MissionProblem> list;
  std::size_t left_out = 0;

  void add(const std::string& file, int line, std::string field, const std::string& what);
  /// A problem the parser or a lookup returned as a status ("<file>:<line>:
  /// ..." and its first field violation).
  void addStatus(const absl::Status& status, const std::string& file);
  /// OK, or INVALID_ARGUMENT MISSION_INVALID: the message lists each
  /// problem, one a line (then how many more); each is a field violation.
  absl::Status status() const;
};

/// Checks a parsed mission against what is registered, before anything
/// flies, and finds every problem at once: a behavior that no system hosts,
/// a parameter the behavior does not have, a literal value of the wrong JSON
/// type or out of the parameter's range, a required parameter missing
/// (bindings are checked when they are resolved). INVALID_ARGUMENT
/// MISSION_INVALID: the message lists each problem with file:line, one a
/// line (at most 50, then how many more); each is a field violation.
MissionProblems checkMissionProblems(const MissionSpec& mission, const BehaviorLookup& lookup);
/// checkMissionProblems as a status.
absl::Status checkMission(const MissionSpec& mission, const BehaviorLookup& lookup);

/// The names in every ${<kind>.<name>} of `text` ("param", "each").
std::vector<std::string> tokenNames(const std::string& text, const std::string& kind);
/// Runs `check` on every string in `value` (lists and objects walked) until
/// one fails.
absl::Status forEachString(const google::protobuf::Value& value,
                           const std::function<absl::Status(const std::string&)>& check);
/// Replaces each ${<kind>.<name>} in the strings of `value` by lookup(name):
/// a whole string by the value itself, inside a text by its text (a list or
/// an object there is INVALID_ARGUMENT). A name lookup() does not know is
/// INVALID_ARGUMENT with unknown(name). Sub-missions' ${param.x} when parsed,
/// loops' ${each.x} when a step starts.
absl::Status substituteTokens(
    google::protobuf::Value* value, const std::string& kind,
    const std::function<const google::protobuf::Value*(const std::string&)>& lookup,
    const std::function<std::string(const std::string&)>& unknown);

/// "GOAL_ACHIEVED", ... for a TerminationCause.
std::string causeName(v1::TerminationCause cause);

}  // namespace behaviorlib::coordinator
