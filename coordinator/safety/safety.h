#pragma once

// SafetyController: the coordinator's per-robot safety actions and policy,
// acting on the vehicle through its FlightController (the platform
// interface), with a preempting lease so that no behavior commands the
// vehicle meanwhile.
//
// Actions (Coordinator.EmergencyLand and Kill):
//   - EmergencyLand: the robot's mission is aborted without its safety steps
//     and its behaviors that command the vehicle (those holding the catalog's
//     `platform_commands` or `motion_reference`) are deactivated, so that
//     they end INTERRUPTED rather than fail under a vehicle that changed
//     state; then EMERGENCY_LAND. The stand-down gets at most
//     `stand_down_budget`: a system that does not answer never delays the
//     landing longer than that.
//   - Kill (with confirm): motors off at once, then the same stand-down.
//
// Policy, checked every `poll`:
//   - the active motion controller (a behavior providing `motion_control`)
//     finishes PROCESS_FAILURE, or the platform's lease failsafe engages
//     while flying (the controller lost its lease): hover, then land; the
//     mission is aborted without its safety steps;
//   - battery below `critical_battery_ratio` while flying: land; the mission
//     is aborted without its safety steps;
//   - the pose estimate leaves the geofence (the running mission's, else the
//     configured one): hover and abort the mission (its safety steps run).
// Each rule fires once per flight (it re-arms when the vehicle has landed).
// The hover before landing lasts `hover_before_land` of the vehicles' time
// (`clock`: simulated time for simulated vehicles).
// A rule that lands does not wait for a stand-down that hangs (a frozen
// system's calls run into their deadline): it lands after its hover and at
// most `stand_down_budget`, keeping its lease alive until the vehicle is down.
// A motion controller from which the coordinator itself took the lease
// fails (PROCESS_FAILURE) because of that: its failure fires no rule.
// Standing a mission down waits (at most `mission_ack_timeout`) until its
// runner has taken the abort before deactivating behaviors, so that the
// mission ends ABORTED with the safety reason rather than FAILED on a step
// the stand-down interrupted.
//
//   SafetyController safety(fleet, missions, log, {.critical_battery_ratio = 0.1});
//   safety.addRobot("drone1", "127.0.0.1:50070");
//   auto said = safety.emergencyLand("drone1", "operator");

#include <atomic>
#include <chrono>
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
#include "behaviorlib/v1/platform.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "coordinator/control/fleet_control.h"
#include "coordinator/control/mission_manager.h"
#include "coordinator/events/fleet_event_log.h"
#include "coordinator/mission/mission_file.h"

namespace behaviorlib::platform {
class FlightControllerClient;
class FlightStateWatcher;
}  // namespace behaviorlib::platform

namespace behaviorlib::channel {
class ChannelClient;
class Subscription;
}  // namespace behaviorlib::channel

namespace prometheus {
class Registry;
}

namespace behaviorlib::coordinator {

struct SafetyOptions {
  /// Battery state of charge (0..1) under which a flying vehicle lands.
  double critical_battery_ratio = 0.10;
  /// How long the vehicle hovers before it lands (hover-then-land rules), in
  /// the vehicles' time (`clock`).
  std::chrono::milliseconds hover_before_land{1000};
  /// The vehicles' time: the hover before landing and the watch until the
  /// vehicle is down run on it (the simulator's SimClock for simulated
  /// vehicles, whose time may run faster or slower than the host's). Null:
  /// the host's steady clock. Must outlive the controller. Waits on the
  /// coordinator's own calls (the stand-down budget, the mission's
  /// acknowledgement, the lease renewals) stay in host time: they bound
  /// gRPC calls, whose deadlines are host time.
  const Clock* clock = nullptr;
  /// How often the policy looks at each robot.
  std::chrono::milliseconds poll{100};
  /// Geofence for robots whose mission has none; unset: none.
  std::optional<Geofence> geofence;
  /// Data channel broker, for the robots' pose estimates (geofence); empty:
  /// no geofence rule.
  std::string channel_address;
  /// How long EmergencyLand, and the rules that land, wait for the
  /// stand-down (mission aborted, commanding behaviors deactivated) before
  /// they land regardless (the stand-down goes on meanwhile).
  std::chrono::milliseconds stand_down_budget{500};
  /// How long a stand-down waits for the mission's runner to take the abort.
  std::chrono::milliseconds mission_ack_timeout{2000};
  /// Where safety actions are counted; none if null.
  CoordinatorMetrics* metrics = nullptr;
};

class SafetyController {
 public:
  SafetyController(FleetControl& fleet, MissionManager& missions, FleetEventLog& log,
                   SafetyOptions options);
  /// Stops (see stop()).
  ~SafetyController();
  SafetyController(const SafetyController&) = delete;
  SafetyController& operator=(const SafetyController&) = delete;

  /// Watches a robot whose FlightController serves at `flight_controller`.
  void addRobot(const std::string& robot_id, const std::string& flight_controller);
  /// Starts the policy thread (after addRobot calls).
  void start();
  /// Stops the policy and waits for actions in progress.
  void stop();

  /// NOT_FOUND for a robot without a flight controller; the platform's
  /// refusal otherwise. Returns what was done.
  absl::StatusOr<std::string> emergencyLand(const std::string& robot_id, const std::string& reason);
  /// INVALID_ARGUMENT unless `confirm`.
  absl::StatusOr<std::string> kill(const std::string& robot_id, bool confirm,
                                   const std::string& reason);

  /// Safety rules fired so far (for tests and metrics), e.g.
  /// "drone1: battery 0.08 below 0.10: landing".
  std::vector<std::string> firedRules() const;

 private:
  struct Robot;

  Robot* find(const std::string& robot_id) const;
  void policyLoop();
  void checkRobot(Robot& robot);
  void onEvents();
  /// Runs a rule's action on the robot's action thread (one at a time).
  /// `trigger` names the rule for the metrics (battery, geofence, ...).
  void fire(Robot& robot, const std::string& trigger, const std::string& rule, bool hover_first,
            bool land, bool abort_with_safety_steps);
  /// Counts a safety action in the metrics.
  void countAction(const std::string& robot_id, const std::string& action,
                   const std::string& trigger);
  /// Aborts the robot's mission and, once its runner has taken the abort,
  /// deactivates its commanding behaviors (unless the mission's safety steps
  /// run: they command the vehicle).
  std::string standDown(const std::string& robot_id, const std::string& reason,
                        bool run_safety_steps);
  /// Takes the vehicle's lease (preempting its holder), first noting the
  /// active motion controllers, whose failure that causes.
  absl::StatusOr<v1::AcquireLeaseResponse> takeLease(Robot& robot);
  /// EMERGENCY_LAND or KILL under a preempting lease, released afterwards.
  absl::StatusOr<std::string> flightAction(Robot& robot, int action, bool confirm);

  FleetControl& fleet_;
  MissionManager& missions_;
  FleetEventLog& log_;
  const SafetyOptions options_;
  // options_.clock, else steady_clock_.
  SteadyClock steady_clock_;
  const Clock& clock_;
  std::unique_ptr<channel::ChannelClient> channel_;

  // The policy thread and the landings wait on mutex_ (Mutex::Await) for a
  // noted failure, a finished stand-down or the stop.
  mutable absl::Mutex mutex_;
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  std::map<std::string, std::unique_ptr<Robot>> robots_ ABSL_GUARDED_BY(mutex_);
  std::vector<std::string> fired_ ABSL_GUARDED_BY(mutex_);
  std::vector<std::thread> actions_ ABSL_GUARDED_BY(mutex_);
  // Started by start() and joined by stop() (the caller's thread).
  std::thread policy_;
  std::unique_ptr<FleetSubscription> subscription_ ABSL_GUARDED_BY(mutex_);
  // Robots whose motion controller failed.
  std::vector<std::string> pending_failures_ ABSL_GUARDED_BY(mutex_);
};

}  // namespace behaviorlib::coordinator
