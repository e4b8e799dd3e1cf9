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
// A parallel step runs each branch in a thread of its own (each branch is a
// Track: its failure, its loops' items, its part of the journaled history);
// the branches share the status, and a branch that decides the step
// interrupts the others. A fleet mission's steps name their robots; its
// safety steps run per robot, the robots at once.
//
// No gRPC: the coordinator's FleetControl (coordinator/control/) implements
// MissionActions (through the catalog's activation plans and its event
// stream); tests fake them.

#include <google/protobuf/struct.pb.h>

#include <atomic>
#include <chrono>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/v1/mission.pb.h"
#include "behaviorlib/v1/platform.pb.h"
#include "behaviorlib/v1/types.pb.h"
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

/// The robots' latest samples on the data channel, for the conditions on
/// the vehicle that a step checks while it runs (`when:`).
class VehicleReader {
 public:
  virtual ~VehicleReader() = default;
  /// The newest FlightStatus on robots/{robot}/flight_state; NOT_FOUND
  /// when there is none.
  virtual absl::StatusOr<v1::FlightStatus> flightStatus(const std::string& robot) = 0;
  /// The newest pose estimate on robots/{robot}/self_localization/pose.
  virtual absl::StatusOr<v1::PoseStamped> poseEstimate(const std::string& robot) = 0;
};

/// One level of a step's position in a mission (MissionStepRecord.node).
struct MissionNode {
  enum class Kind { kStep, kFallback, kCall, kIteration, kBranch };
  Kind kind = Kind::kStep;
  int index = 0;
  /// kCall, kIteration, kBranch: the attempt of the call, loop or parallel
  /// step whose steps these are
  int call_attempt = 0;
  int iteration = 0;  ///< kIteration: which one; kBranch: which branch (from 0)
  bool operator==(const MissionNode&) const = default;
};
using Position = std::vector<MissionNode>;

/// "steps/2", "steps/2/fallback/0", "steps/2/attempt/1/call/steps/0",
/// "steps/2/attempt/1/iteration/3/steps/0", "steps/2/attempt/1/branch/0/steps/1".
std::string nodeText(const Position& position);
/// nodeText's inverse; nullopt for text it does not make.
std::optional<Position> parseNode(const std::string& text);

/// What a MissionRunner reads besides its actions and beliefs.
struct MissionRunnerOptions {
  /// Measures the waits' limits and the vehicle conditions' staleness
  /// (the vehicles' time; null: the host's steady clock).
  const Clock* clock = nullptr;
  /// Reads the vehicles' topics for `when:` conditions (null: a step with
  /// conditions ends PROCESS_FAILURE; the manager refuses such a mission).
  VehicleReader* vehicles = nullptr;
};

class MissionRunner {
 public:
  /// Receives the mission's status after every change (runner thread; the
  /// runner acts only after it returns).
  using OnChange = std::function<void(const v1::MissionStatus&)>;

  using Options = MissionRunnerOptions;

  /// A new mission. `source` is the mission file's text (kept in the status
  /// so that a restarted coordinator can parse it again). What `options`
  /// points to must outlive the runner.
  MissionRunner(MissionSpec spec, std::string mission_id, std::string robot_id, std::string source,
                MissionActions& actions, BeliefStore& beliefs, OnChange on_change,
                Options options = {});
  /// A mission recorded as `status` (not finished), continued where it was.
  MissionRunner(MissionSpec spec, const v1::MissionStatus& status, MissionActions& actions,
                BeliefStore& beliefs, OnChange on_change, Options options = {});
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
  /// Deactivates the current behaviors, runs the safety steps (unless
  /// `run_safety` is false: a safety action lands the vehicle itself; with
  /// `robot`, only that robot's are skipped), ends ABORTED.
  /// FAILED_PRECONDITION when the mission already ended.
  absl::Status abort(const std::string& reason, bool run_safety = true,
                     const std::string& robot = "");

  v1::MissionStatus status() const;
  bool finished() const;
  /// Waits until the mission ends (or `timeout`); true when it ended.
  bool waitFinished(std::chrono::milliseconds timeout) const;

  /// How often the runner looks at pause/abort requests while it waits.
  static constexpr std::chrono::milliseconds kPoll{50};

 private:
  /// How a run of steps ended: went on; the mission fails (Track::failure);
  /// an abort was requested; the coordinator stops; a parallel step around
  /// was decided by another branch.
  enum class Flow { kDone, kAbort, kAbortRequested, kQuit, kInterrupted };

  /// What one thread of the mission carries: the main sequence's, or a
  /// parallel branch's.
  struct Track {
    std::string failure;  // why it is failing (set on kAbort)
    // The cause of the step whose `on:` aborted (what a call, a loop or a
    // branch ends with); empty when the abort has another reason.
    std::string failed_cause;
    // The items of the for_each loops around the running step (innermost last).
    std::vector<std::pair<std::string, google::protobuf::Value>> items;
    // The journaled records below this track, when resuming (the last one is
    // where it was); cleared once it resumed.
    std::vector<v1::MissionStepRecord> resume_from;
    // The parallel steps around it (ids in interrupted_).
    std::vector<int> parallels;
  };

  void run();
  /// Runs `steps`, whose positions are `prefix` and then `kind` (a step,
  /// a fallback's step, or a step of the attempt `call_attempt` of a call,
  /// an iteration or a branch); `resume` is where to go on from, below
  /// `prefix`.
  Flow runList(const std::vector<MissionStep>& steps, const Position& prefix,
               MissionNode::Kind kind, int call_attempt, Position resume, int iteration, Track& t);
  Flow runStep(const MissionStep& step, const Position& path, Position resume_tail, Track& t);
  /// A call of a sub-mission, a loop or a parallel step: its steps, ending
  /// like a behavior (the cause of the step that failed it), and its own
  /// `on:`.
  Flow runCall(const MissionStep& step, const Position& path, Position resume_tail,
               std::optional<v1::MissionStepRecord> recorded, Track& t);
  /// A wait_for step.
  Flow runWait(const MissionStep& step, const Position& path,
               std::optional<v1::MissionStepRecord> recorded, Track& t);
  /// Runs a call's, a loop's or a parallel step's steps (attempt `attempt`,
  /// resuming at `tail`): GOAL_ACHIEVED when they went on, else the cause
  /// that failed them (REFUSED for a loop that could not start), or nullopt
  /// with `flow` for an end of the mission.
  std::optional<std::string> runBody(const MissionStep& step, const Position& path, int attempt,
                                     const Position& tail, std::string* message, Flow* flow,
                                     Track& t);
  /// The steps of a loop, an iteration at a time.
  std::optional<std::string> runLoop(const MissionStep& step, const Position& path, int attempt,
                                     const Position& tail, std::string* message, Flow* flow,
                                     Track& t);
  /// The branches of a parallel step, each in a thread.
  std::optional<std::string> runParallel(const MissionStep& step, const Position& path, int attempt,
                                         std::string* message, Flow* flow, Track& t);
  /// `parameters` with each ${each.<name>} of the loops around replaced.
  static absl::StatusOr<google::protobuf::Struct> withItems(
      const google::protobuf::Struct& parameters, const Track& t);
  /// What the step's `on:` does after `cause`: nullopt to try again
  /// (`attempt` raised), else the flow (t.failure and t.failed_cause set on
  /// an abort; a fallback run).
  std::optional<Flow> afterCause(const MissionStep& step, const Position& path,
                                 const std::string& cause, const std::string& message, int* attempt,
                                 Track& t);
  Flow waitFor(const MissionStep& step, const std::string& activation_id,
               FinishedActivation* finished, Track& t);
  /// The step's `when:` conditions now: the cause and message of the first
  /// that holds (or of a stale topic: PROCESS_FAILURE), else nullopt.
  /// `seen` keeps, per topic, the last stamp and when it was first seen.
  struct TopicSeen {
    int64_t stamp_ns = -1;
    TimePoint since;
  };
  std::optional<FinishedActivation> vehicleConditionHolds(const MissionStep& step,
                                                          std::map<std::string, TopicSeen>* seen);
  Flow waitWhilePaused(const Track& t);
  void runSafety(const std::string& failure);
  void deactivateRecurrent();
  std::optional<std::string> recurrentFinished();
  const MissionAction* actionFor(const MissionStep& step, const std::string& cause) const;
  bool conditionHolds(const BeliefCondition& c) const;
  /// Whether `wait` holds now, and what it waits for (a record's text).
  bool waitHolds(const MissionWait& wait) const;
  void rememberAll(const MissionStep& step, const Track& t);
  /// The robot `step` commands.
  const std::string& robotOf(const MissionStep& step) const;
  /// Whether a parallel step around `t` was decided by another branch.
  bool interruptedLocked(const Track& t) const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);
  bool interrupted(const Track& t) const;
  /// The record of the call, loop, parallel or wait step at `node` and
  /// `attempt` (journaled before a restart), or -1.
  int findRecord(const std::string& node, int attempt) const;
  /// Marks the record `index` INTERRUPTED after `flow` stopped it.
  void recordStopped(int index, Flow flow);

  // Status updates (each one published through on_change_).
  int addRecord(v1::MissionStepRecord record);
  void updateRecord(int index, const std::function<void(v1::MissionStepRecord&)>& change);
  void setState(v1::MissionState state, const std::string& message = "");
  /// Hands a copy of the status to on_change_ (called without the mutex).
  void publish();
  std::string stepLabel(const MissionStep& step, const Position& path) const;

  MissionSpec spec_;
  const std::string robot_;  // the mission's robot (steps that name none)
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
  std::vector<std::string> skip_safety_of_ ABSL_GUARDED_BY(mutex_);  // robots landed by safety
  std::string abort_reason_ ABSL_GUARDED_BY(mutex_);
  // The parallel steps running, by id: true once decided (its other
  // branches then stop).
  std::map<int, bool> parallels_ ABSL_GUARDED_BY(mutex_);
  int next_parallel_ ABSL_GUARDED_BY(mutex_) = 0;
  // Set before the thread starts, then read only:
  struct Recurrent {
    std::string robot;
    std::string behavior;
    std::string activation_id;
  };
  std::vector<Recurrent> recurrent_;
  std::vector<v1::MissionStepRecord> resume_from_;  // history when resuming
  bool resuming_ = false;
  SteadyClock steady_clock_;
  const Clock& clock_;  // the given clock, else steady_clock_
  VehicleReader* const vehicles_;
  std::thread thread_;
};

}  // namespace behaviorlib::coordinator
