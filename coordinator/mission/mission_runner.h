#pragma once

// MissionRunner: runs one mission (a MissionSpec) on one robot in a thread of
// its own: activates its recurrent behaviors, then each step's behavior, waits
// for its finished event, and follows what the step says for the termination
// cause (continue, retry, fallback, abort); on abort it runs the safety steps.
// Pause, resume and abort come from other threads.
//
// Exactly once across coordinator restarts: every change of the mission's
// state is handed to `on_change` (the coordinator journals it) BEFORE the
// runner acts on it, and every activation carries a request id derived from
// the mission id, the step's position and the attempt
// ("<mission>/steps/2/attempt/1"). A restarted coordinator builds the runner
// with resume() from the journaled status: the step that was running is
// activated again with the same request id, which the behavior system
// answers with the same activation (nothing is activated twice), and its
// finished event (replayed if it happened meanwhile) decides what comes next.
//
// No gRPC: the coordinator's FleetControl (coordinator/control/) implements
// MissionActions (through the catalog's activation plans and its event
// stream); tests fake them.

#include <google/protobuf/struct.pb.h>

#include <atomic>
#include <chrono>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/v1/mission.pb.h"
#include "coordinator/belief/belief_store.h"
#include "coordinator/mission/mission_file.h"

namespace behaviorlib::coordinator {

struct FinishedActivation {
  v1::TerminationCause cause = v1::TERMINATION_CAUSE_UNSPECIFIED;
  std::string message;
};

class MissionActions {
 public:
  virtual ~MissionActions() = default;
  /// Activates `behavior` on `robot`; the same `request_id` gives back the
  /// same activation id.
  virtual absl::StatusOr<std::string> activate(const std::string& robot,
                                               const std::string& behavior,
                                               const google::protobuf::Struct& parameters,
                                               const std::string& request_id) = 0;
  /// OK when the behavior is (now) inactive.
  virtual absl::Status deactivate(const std::string& robot, const std::string& behavior) = 0;
  virtual absl::Status pause(const std::string& robot, const std::string& behavior) = 0;
  virtual absl::Status resume(const std::string& robot, const std::string& behavior) = 0;
  /// The finished event of `activation_id`, also when it happened before
  /// this call; nullopt when none arrives within `timeout`.
  virtual std::optional<FinishedActivation> awaitFinished(const std::string& robot,
                                                          const std::string& activation_id,
                                                          std::chrono::milliseconds timeout) = 0;
};

/// One level of a step's position in a mission (MissionStepRecord.node).
struct MissionNode {
  enum class Kind { kStep, kFallback, kCall, kIteration };
  Kind kind = Kind::kStep;
  int index = 0;
  /// kCall, kIteration: the attempt of the call or loop whose steps these are
  int call_attempt = 0;
  int iteration = 0;  ///< kIteration: which one, from 0
  bool operator==(const MissionNode&) const = default;
};
using Position = std::vector<MissionNode>;

/// "steps/2", "steps/2/fallback/0", "steps/2/attempt/1/call/steps/0",
/// "steps/2/attempt/1/iteration/3/steps/0".
std::string nodeText(const Position& position);
/// nodeText's inverse; nullopt for text it does not make.
std::optional<Position> parseNode(const std::string& text);

class MissionRunner {
 public:
  /// Receives the mission's status after every change (runner thread; the
  /// runner acts only after it returns).
  using OnChange = std::function<void(const v1::MissionStatus&)>;

  /// A new mission. `source` is the mission file's text (kept in the status
  /// so that a restarted coordinator can parse it again).
  MissionRunner(MissionSpec spec, std::string mission_id, std::string robot_id, std::string source,
                MissionActions& actions, BeliefStore& beliefs, OnChange on_change);
  /// A mission recorded as `status` (not finished), continued where it was.
  MissionRunner(MissionSpec spec, const v1::MissionStatus& status, MissionActions& actions,
                BeliefStore& beliefs, OnChange on_change);
  /// Stops the thread without aborting the mission (it stays RUNNING in the
  /// journal, to be resumed by the next coordinator).
  ~MissionRunner();
  MissionRunner(const MissionRunner&) = delete;
  MissionRunner& operator=(const MissionRunner&) = delete;

  void start();
  /// FAILED_PRECONDITION when the mission is not running (or already paused).
  absl::Status pause();
  /// FAILED_PRECONDITION when the mission is not paused.
  absl::Status resume();
  /// Deactivates the current behavior, runs the safety steps (unless
  /// `run_safety` is false: a safety action lands the vehicle itself), ends
  /// ABORTED. FAILED_PRECONDITION when the mission already ended.
  absl::Status abort(const std::string& reason, bool run_safety = true);

  v1::MissionStatus status() const;
  bool finished() const;
  /// Waits until the mission ends (or `timeout`); true when it ended.
  bool waitFinished(std::chrono::milliseconds timeout) const;

  /// How often the runner looks at pause/abort requests while it waits.
  static constexpr std::chrono::milliseconds kPoll{50};

 private:
  enum class Flow { kDone, kAbort, kAbortRequested, kQuit };

  void run();
  /// Runs `steps`, whose positions are `prefix` and then `kind` (a step,
  /// a fallback's step, or a step of the call's attempt `call_attempt`);
  /// `resume` is where to go on from, below `prefix`.
  Flow runList(const std::vector<MissionStep>& steps, const Position& prefix,
               MissionNode::Kind kind, int call_attempt, Position resume, int iteration = 0);
  Flow runStep(const MissionStep& step, const Position& path, Position resume_tail);
  /// A call of a sub-mission: its steps, ending like a behavior (the cause
  /// of the step that failed it), and its own `on:`.
  Flow runCall(const MissionStep& step, const Position& path, Position resume_tail,
               std::optional<v1::MissionStepRecord> recorded);
  /// Runs a call's or a loop's steps (attempt `attempt`, resuming at
  /// `tail`): GOAL_ACHIEVED when they all went on, else the cause of the step
  /// that failed them (REFUSED for a loop that could not start), or nullopt
  /// with `flow` for an end of the mission.
  std::optional<std::string> runBody(const MissionStep& step, const Position& path, int attempt,
                                     const Position& tail, std::string* message, Flow* flow);
  /// The steps of a loop, an iteration at a time.
  std::optional<std::string> runLoop(const MissionStep& step, const Position& path, int attempt,
                                     const Position& tail, std::string* message, Flow* flow);
  /// `parameters` with each ${each.<name>} of the loops around replaced.
  absl::StatusOr<google::protobuf::Struct> withItems(const google::protobuf::Struct& parameters);
  /// What the step's `on:` does after `cause`: nullopt to try again
  /// (`attempt` raised), else the flow (failure_ and failed_cause_ set on an
  /// abort; a fallback run).
  std::optional<Flow> afterCause(const MissionStep& step, const Position& path,
                                 const std::string& cause, const std::string& message,
                                 int* attempt);
  Flow waitFor(const MissionStep& step, const std::string& activation_id,
               FinishedActivation* finished);
  Flow waitWhilePaused();
  void runSafety();
  void deactivateRecurrent();
  std::optional<std::string> recurrentFinished();
  const MissionAction* actionFor(const MissionStep& step, const std::string& cause) const;
  bool conditionHolds(const BeliefCondition& c) const;
  void rememberAll(const MissionStep& step);

  // Status updates (each one published through on_change_).
  int addRecord(v1::MissionStepRecord record);
  void updateRecord(int index, const std::function<void(v1::MissionStepRecord&)>& change);
  void setState(v1::MissionState state, const std::string& message = "");
  /// Hands a copy of the status to on_change_ (called without the mutex).
  void publish();
  std::string stepLabel(const MissionStep& step, const Position& path) const;

  MissionSpec spec_;
  MissionActions& actions_;
  BeliefStore& beliefs_;
  OnChange on_change_;

  // The runner waits on mutex_ (Mutex::Await) while paused; waitFinished
  // for done_.
  mutable absl::Mutex mutex_;
  v1::MissionStatus status_ ABSL_GUARDED_BY(mutex_);
  bool quit_ ABSL_GUARDED_BY(mutex_) = false;
  bool abort_requested_ ABSL_GUARDED_BY(mutex_) = false;
  bool pause_requested_ ABSL_GUARDED_BY(mutex_) = false;
  bool done_ ABSL_GUARDED_BY(mutex_) = false;
  bool skip_safety_ ABSL_GUARDED_BY(mutex_) = false;
  std::string abort_reason_ ABSL_GUARDED_BY(mutex_);
  // The runner thread's own (not guarded):
  std::string failure_;  // why the mission is failing (set before the safety steps)
  // The cause of the step whose `on:` aborted (what a call ends with);
  // empty when the abort has another reason (a recurrent behavior ended).
  std::string failed_cause_;
  // The items of the for_each loops around the running step (innermost last).
  std::vector<std::pair<std::string, google::protobuf::Value>> items_;
  std::vector<std::pair<std::string, std::string>> recurrent_;  // behavior, activation id
  std::vector<v1::MissionStepRecord> resume_from_;              // history when resuming
  bool resuming_ = false;
  std::thread thread_;
};

}  // namespace behaviorlib::coordinator
