#pragma once

// MissionManager: the coordinator's missions. Parses and checks a mission
// file against what the robot's systems registered (nothing flies before the
// file is known good), runs it with a MissionRunner over FleetControl, and
// journals every status change before the runner acts on it. At start the
// journal's statuses are restored; a mission that was running is resumed as
// soon as every behavior it names is served again, and the runner's request
// ids make the behavior systems answer a repeated activation with the
// activation they remember (nothing is activated twice).
//
//   MissionManager missions(fleet, registry, beliefs, journal.get(), {});
//   missions.restore(status);          // each journaled MissionStatus, in order
//   missions.resumeRestored();         // once the server is up
//   auto started = missions.start(request);
//   missions.stop();                   // shutdown: running missions stay RUNNING
//
// Thread-safe.

#include <chrono>
#include <cstdint>
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
#include "behaviorlib/durable/v1/journal.pb.h"
#include "behaviorlib/server_kit/confined_files.h"
#include "behaviorlib/v1/coordinator.pb.h"
#include "behaviorlib/v1/mission.pb.h"
#include "coordinator/belief/belief_store.h"
#include "coordinator/control/fleet_control.h"
#include "coordinator/durable/journal.h"
#include "coordinator/metrics/coordinator_metrics.h"
#include "coordinator/mission/mission_runner.h"
#include "coordinator/registry/registry.h"

namespace behaviorlib::coordinator {

struct MissionManagerOptions {
  /// How long a restored mission waits for its robot's systems to be back
  /// before it is marked FAILED.
  std::chrono::milliseconds resume_wait{60000};
  /// Where StartMission.file_path may read (the default refuses every path:
  /// clients send the text).
  server_kit::ConfinedDirectory mission_files;
  /// Largest mission, as text or file.
  size_t max_mission_bytes = 1 << 20;
  /// Ended missions kept (GetMission, ListMissions, the journal): at most
  /// this many, the most recent, and none that ended longer ago than
  /// `max_ended_age`. Pruned when a mission starts and after a restart.
  size_t max_ended_missions = 1000;
  std::chrono::seconds max_ended_age{7 * 24 * 3600};
  /// The clock that end times are compared with (missions' times are wall
  /// times); a test gives its own.
  std::function<google::protobuf::Timestamp()> now;
  /// The vehicles' clock, which the missions' waits are measured on (null:
  /// the host's steady clock). Must outlive the manager.
  const Clock* clock = nullptr;
  /// Reads the vehicles' topics for the steps' `when:` conditions (null: a
  /// mission with conditions is refused). Must outlive the manager.
  VehicleReader* vehicles = nullptr;
  /// Where missions started and ended are counted; none if null.
  CoordinatorMetrics* metrics = nullptr;
};

class MissionManager {
 public:
  MissionManager(FleetControl& fleet, Registry& registry, BeliefStore& beliefs, Journal* journal,
                 MissionManagerOptions options = {});
  /// Stops (see stop()).
  ~MissionManager();
  MissionManager(const MissionManager&) = delete;
  MissionManager& operator=(const MissionManager&) = delete;

  /// One journaled status (journal replay, before resumeRestored()); the
  /// latest one per mission id wins.
  void restore(const v1::MissionStatus& status);
  /// Resumes every restored mission that had not ended, each once its
  /// behaviors are routable again (on a thread of its own).
  void resumeRestored();

  /// INVALID_ARGUMENT naming file, line and problem for a bad mission;
  /// FAILED_PRECONDITION when the robot runs another mission; an existing
  /// mission id returns that mission.
  absl::StatusOr<v1::MissionStatus> start(const v1::StartMissionRequest& request);
  /// Checks a mission as start() would, without starting it: every
  /// problem as data (a mission with problems is not an error), and each
  /// step's plan. The request's own errors (no source, a file outside the
  /// mission directory, a text too long) are statuses, as for start().
  absl::StatusOr<v1::CheckMissionResponse> check(const v1::CheckMissionRequest& request) const;
  absl::StatusOr<v1::MissionStatus> get(const std::string& mission_id) const;
  /// Newest first.
  std::vector<v1::MissionStatus> list() const;
  absl::StatusOr<v1::MissionStatus> pause(const std::string& mission_id);
  absl::StatusOr<v1::MissionStatus> resume(const std::string& mission_id);
  /// `run_safety` false with `robot`: only that robot's safety steps are
  /// skipped (a fleet mission's other robots still run theirs).
  absl::StatusOr<v1::MissionStatus> abort(const std::string& mission_id, const std::string& reason,
                                          bool run_safety = true, const std::string& robot = "");
  /// The id of the mission that commands the robot and has not ended, if
  /// any (a fleet mission commands several).
  std::optional<std::string> runningMissionOf(const std::string& robot_id) const;
  /// The geofence of the robot's running mission, with the mission's id.
  std::optional<std::pair<std::string, Geofence>> geofenceOf(const std::string& robot_id) const;

  /// Calls `listener` with the mission's status now and after every change
  /// (from the runner's thread; it must not block). Returns a token for
  /// unwatch(); NOT_FOUND for an unknown id.
  using Listener = std::function<void(const v1::MissionStatus&)>;
  absl::StatusOr<uint64_t> watch(const std::string& mission_id, Listener listener);
  void unwatch(uint64_t token);

  /// Journal records of the current state (beliefs are the store's), for
  /// compaction.
  std::vector<durable::v1::JournalRecord> snapshot() const;

  /// Stops every runner without ending its mission (the journal keeps it
  /// RUNNING for the next coordinator).
  void stop();

 private:
  struct Entry {
    v1::MissionStatus status;
    // Null once the mission has ended (its runner is then released) or when
    // it was restored ended from the journal.
    std::shared_ptr<MissionRunner> runner;
    std::optional<Geofence> geofence;
    uint64_t order = 0;  // start order, for list()
  };

  void onChange(const v1::MissionStatus& status);
  /// Runs `request` on the mission's runner: NOT_FOUND for an unknown id,
  /// FAILED_PRECONDITION when it is not running in this coordinator.
  absl::StatusOr<v1::MissionStatus> control(
      const std::string& mission_id, const std::function<absl::Status(MissionRunner&)>& request);
  // A mission's text and the name its problems give it.
  struct Source {
    std::string text;
    std::string file;
  };
  template <class Request>
  absl::StatusOr<Source> readSource(const Request& request) const;
  /// Reads the files a mission imports from the mission directory (null
  /// without one: a mission then cannot import).
  ImportReader importReader() const;
  /// The problems of `spec` for `robot_id` (and every robot its steps
  /// name) against the registry; `unregistered` receives the first robot
  /// with no registered system (the steps are then not checked).
  MissionProblems problemsAgainstRegistry(const MissionSpec& spec, const std::string& robot_id,
                                          std::string* unregistered) const;
  absl::Status checkAgainstRegistry(const MissionSpec& spec, const std::string& robot_id) const;
  /// A problem for each binding to a belief that is not in memory, that no
  /// step of the mission writes (its `remember`, or its behavior's catalog
  /// `writes`) and that no step waits for.
  void unwrittenBeliefProblems(const MissionSpec& spec, const std::string& robot_id,
                               MissionProblems* problems) const;
  /// Each step's plan, in file order (v1::MissionStepPlan).
  void planSteps(const MissionSpec& spec, const std::string& robot_id,
                 v1::CheckMissionResponse* response) const;
  bool behaviorsRoutable(const MissionSpec& spec, const std::string& robot_id,
                         std::string* missing) const;
  void resumeOne(const std::string& mission_id);
  static bool ended(const v1::MissionStatus& status);
  /// Moves the ended missions beyond the retention limits into `pruned`
  /// (destroyed by the caller, outside the lock).
  void pruneLocked(std::vector<Entry>* pruned) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);
  /// Sets the retained-missions and runners gauges.
  void countLocked() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);

  FleetControl& fleet_;
  Registry& registry_;
  BeliefStore& beliefs_;
  Journal* journal_;
  const MissionManagerOptions options_;

  mutable absl::Mutex mutex_;
  bool stopped_ ABSL_GUARDED_BY(mutex_) = false;
  std::map<std::string, Entry> missions_ ABSL_GUARDED_BY(mutex_);
  uint64_t next_order_ ABSL_GUARDED_BY(mutex_) = 1;
  uint64_t next_token_ ABSL_GUARDED_BY(mutex_) = 1;
  std::map<uint64_t, std::pair<std::string, Listener>> listeners_ ABSL_GUARDED_BY(mutex_);
  std::vector<std::thread> resumers_ ABSL_GUARDED_BY(mutex_);
  // Runners of missions that have ended, released from their entries (which
  // keep only the final status) and destroyed, joining their threads, by the
  // next start() or by stop(): an ended mission keeps neither its parsed
  // specification nor its thread.
  std::vector<std::shared_ptr<MissionRunner>> finished_ ABSL_GUARDED_BY(mutex_);
};

}  // namespace behaviorlib::coordinator
