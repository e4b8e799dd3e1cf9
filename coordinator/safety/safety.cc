#include "coordinator/safety/safety.h"

#include <algorithm>
#include <cstdio>
#include <set>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/error_details.h"
#include "behaviorlib/flight_common/topics.h"
#include "behaviorlib/platform/flight_controller_client.h"
#include "behaviorlib/platform/flight_state_watcher.h"
#include "behaviorlib/v1/platform.pb.h"

namespace behaviorlib::coordinator {

namespace {

bool airborne(v1::FlightState state) {
  return state == v1::FLIGHT_STATE_TAKING_OFF || state == v1::FLIGHT_STATE_FLYING ||
         state == v1::FLIGHT_STATE_HOVERING;
}

constexpr char kSafetyHolderSuffix[] = "/coordinator-safety";
constexpr std::chrono::seconds kSafetyLeaseTtl{10};
// How often a safety action renews its lease (host time), far within the
// ttl even when simulated time runs many times faster.
constexpr std::chrono::milliseconds kRenewPeriod{100};

// A span of the vehicle's time (its Clock) from construction. A clock that
// is not valid (no simulated time yet) counts the span in host time, and one
// that went back (a restarted simulator, a new time line) ends it: a hover
// never waits for time that will not come.
class VehicleTimer {
 public:
  VehicleTimer(const Clock& clock, Duration span)
      : clock_(clock),
        span_(span),
        vehicle_time_(clock.valid()),
        start_(clock.now()),
        host_start_(std::chrono::steady_clock::now()) {}

  bool done() const { return remaining() <= Duration::zero(); }

  /// How long (host time) to wait before looking again: at most `cap`.
  std::chrono::nanoseconds wallWait(std::chrono::nanoseconds cap) const {
    const Duration left = remaining();
    if (left <= Duration::zero()) return cap;
    return std::min(cap, vehicle_time_ ? clock_.wallWaitFor(left) : left);
  }

 private:
  Duration remaining() const {
    if (!vehicle_time_) return span_ - (std::chrono::steady_clock::now() - host_start_);
    const TimePoint now = clock_.now();
    if (now < start_) return Duration::zero();
    return span_ - (now - start_);
  }

  const Clock& clock_;
  const Duration span_;
  const bool vehicle_time_;
  const TimePoint start_;
  const std::chrono::steady_clock::time_point host_start_;
};

absl::Status noFlightController(const std::string& robot_id) {
  return errors::withReason(
      absl::NotFoundError(absl::StrCat("no flight controller known for robot '", robot_id,
                                       "': start the coordinator with --flight-controller ",
                                       robot_id, "=host:port")),
      v1::UNKNOWN_ROBOT, {{"robot", robot_id}});
}

}  // namespace

struct SafetyController::Robot {
  Robot(std::string id, const std::string& address)
      : robot_id(std::move(id)),
        fc(std::make_unique<platform::FlightControllerClient>(address, robot_id)),
        watcher(std::make_unique<platform::FlightStateWatcher>(*fc)) {}

  std::string robot_id;
  std::unique_ptr<platform::FlightControllerClient> fc;
  std::unique_ptr<platform::FlightStateWatcher> watcher;
  std::unique_ptr<channel::Subscription> pose_subscription;

  // Guarded by SafetyController::mutex_ (not annotated: a nested struct's
  // field cannot name its controller's mutex to the thread-safety analysis).
  bool acting = false;  // an action thread is running for this robot
  bool failure_fired = false, battery_fired = false, geofence_fired = false;
  // Motion controllers active when the coordinator took the lease: they fail
  // because of it, which is no controller failure.
  std::set<std::string> preempted_controllers;
  std::optional<v1::PoseStamped> pose;
  std::chrono::steady_clock::time_point pose_received;
};

SafetyController::SafetyController(FleetControl& fleet, MissionManager& missions,
                                   FleetEventLog& log, SafetyOptions options)
    : fleet_(fleet),
      missions_(missions),
      log_(log),
      options_(std::move(options)),
      clock_(options_.clock != nullptr ? *options_.clock : steady_clock_) {
  if (!options_.channel_address.empty()) {
    channel_ = std::make_unique<channel::ChannelClient>(options_.channel_address);
  }
}

SafetyController::~SafetyController() { stop(); }

void SafetyController::addRobot(const std::string& robot_id, const std::string& flight_controller) {
  auto robot = std::make_unique<Robot>(robot_id, flight_controller);
  Robot* raw = robot.get();
  if (channel_) {
    raw->pose_subscription = channel_->subscribeTyped<v1::PoseStamped>(
        flight::poseEstimateTopic(robot_id), {}, [this, raw](const v1::PoseStamped& pose) {
          absl::MutexLock lock(&mutex_);
          raw->pose = pose;
          raw->pose_received = std::chrono::steady_clock::now();
        });
  }
  absl::MutexLock lock(&mutex_);
  robots_[robot_id] = std::move(robot);
}

void SafetyController::start() {
  FleetSubscribeOptions from_now;
  from_now.since_seq = log_.latestSeq();
  auto subscription = log_.subscribe(from_now, [this] { onEvents(); });
  {
    absl::MutexLock lock(&mutex_);
    subscription_ = std::move(subscription);
  }
  onEvents();
  policy_ = std::thread([this] { policyLoop(); });
}

void SafetyController::stop() {
  std::vector<std::thread> actions;
  {
    absl::MutexLock lock(&mutex_);
    if (stopping_ && !policy_.joinable() && actions_.empty()) return;
    stopping_ = true;  // the policy's Await sees it at this unlock
  }
  if (policy_.joinable()) policy_.join();
  {
    absl::MutexLock lock(&mutex_);
    actions.swap(actions_);
  }
  for (auto& t : actions) t.join();
  std::unique_ptr<FleetSubscription> subscription;
  {
    absl::MutexLock lock(&mutex_);
    subscription.swap(subscription_);
  }
  if (subscription) subscription->cancel();
}

SafetyController::Robot* SafetyController::find(const std::string& robot_id) const {
  absl::MutexLock lock(&mutex_);
  auto it = robots_.find(robot_id);
  return it == robots_.end() ? nullptr : it->second.get();
}

void SafetyController::countAction(const std::string& robot_id, const std::string& action,
                                   const std::string& trigger) {
  if (options_.metrics == nullptr) return;
  options_.metrics->safety_actions
      .Add({{"robot", robot_id}, {"action", action}, {"trigger", trigger}})
      .Increment();
}

std::vector<std::string> SafetyController::firedRules() const {
  absl::MutexLock lock(&mutex_);
  return fired_;
}

void SafetyController::onEvents() {
  // Runs on the log's appending thread: only note what happened (the
  // policy's Await sees pending_failures_ at the unlock).
  absl::MutexLock lock(&mutex_);
  if (!subscription_) return;
  while (FleetEventPtr event = subscription_->pop()) {
    if (!event->has_behavior_event()) continue;
    const v1::BehaviorEvent& e = event->behavior_event();
    if (!e.has_finished() || e.finished().cause() != v1::TERMINATION_CAUSE_PROCESS_FAILURE) {
      continue;
    }
    const CatalogBehavior* entry = fleet_.catalog()->find(e.behavior());
    if (entry == nullptr) continue;
    bool controller = false;
    for (const auto& cap : entry->provides) controller |= cap == "motion_control";
    auto robot = robots_.find(e.robot_id());
    if (!controller || robot == robots_.end()) continue;
    if (robot->second->preempted_controllers.contains(e.activation_id())) continue;
    pending_failures_.push_back(e.robot_id() + "\n" + e.behavior() + ": " + e.finished().message());
  }
}

void SafetyController::policyLoop() {
  for (;;) {
    std::vector<Robot*> robots;
    std::vector<std::string> failures;
    {
      absl::MutexLock lock(&mutex_);
      auto ready = [&]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
        return stopping_ || !pending_failures_.empty();
      };
      mutex_.AwaitWithTimeout(absl::Condition(&ready), absl::FromChrono(options_.poll));
      if (stopping_) return;
      failures.swap(pending_failures_);
      for (auto& [id, robot] : robots_) robots.push_back(robot.get());
    }
    for (const auto& failure : failures) {
      const auto split = failure.find('\n');
      Robot* robot = find(failure.substr(0, split));
      if (robot == nullptr) continue;
      auto status = robot->watcher->latest();
      if (status.ok() && !airborne(status->state())) continue;
      bool fire_now = false;
      {
        absl::MutexLock lock(&mutex_);
        fire_now = !robot->failure_fired && !robot->acting;
        robot->failure_fired = true;
      }
      if (fire_now) {
        fire(*robot, "controller_failure",
             absl::StrCat("motion controller failed (", failure.substr(split + 1),
                          "): hover, then land"),
             true, true, false);
      }
    }
    for (Robot* robot : robots) checkRobot(*robot);
  }
}

void SafetyController::checkRobot(Robot& robot) {
  auto status = robot.watcher->latest();
  if (!status.ok()) return;
  const bool flying = airborne(status->state());
  std::string rule, trigger;
  bool hover_first = false, land = false, with_safety_steps = false;
  {
    absl::MutexLock lock(&mutex_);
    if (!flying) {
      if (status->state() == v1::FLIGHT_STATE_LANDED && !robot.acting) {
        robot.failure_fired = robot.battery_fired = robot.geofence_fired = false;
        robot.preempted_controllers.clear();
      }
      return;
    }
    if (robot.acting) return;
    if (!robot.failure_fired && status->failsafe_active()) {
      robot.failure_fired = true;
      trigger = "lease_failsafe";
      rule =
          "the platform's lease failsafe engaged (the motion controller lost its lease): "
          "hover, then land";
      hover_first = land = true;
    } else if (!robot.battery_fired && status->battery_ratio() < options_.critical_battery_ratio) {
      robot.battery_fired = true;
      trigger = "battery";
      rule = absl::StrFormat("battery %.2f below the critical %.2f: land", status->battery_ratio(),
                             options_.critical_battery_ratio);
      land = true;
    } else if (!robot.geofence_fired && robot.pose &&
               std::chrono::steady_clock::now() - robot.pose_received < std::chrono::seconds(2)) {
      std::optional<Geofence> fence = options_.geofence;
      std::string whose = "the configured geofence";
      if (auto mission = missions_.geofenceOf(robot.robot_id)) {
        fence = mission->second;
        whose = "the geofence of mission " + mission->first;
      }
      const auto& p = robot.pose->pose().position_m();
      if (fence && !fence->contains(p.x(), p.y(), p.z())) {
        robot.geofence_fired = true;
        trigger = "geofence";
        rule = absl::StrFormat("left %s at (%.2f, %.2f, %.2f): hover and abort the mission", whose,
                               p.x(), p.y(), p.z());
        hover_first = true;
        with_safety_steps = true;
      }
    }
  }
  if (!rule.empty()) fire(robot, trigger, rule, hover_first, land, with_safety_steps);
}

void SafetyController::fire(Robot& robot, const std::string& trigger, const std::string& rule,
                            bool hover_first, bool land, bool abort_with_safety_steps) {
  const std::string said = robot.robot_id + ": " + rule;
  std::fprintf(stderr, "coordinator: safety: %s\n", said.c_str());
  absl::MutexLock lock(&mutex_);
  if (stopping_) return;
  fired_.push_back(said);
  const char* action = land ? (hover_first ? "hover_then_land" : "land") : "hover_and_abort";
  countAction(robot.robot_id, action, trigger);
  robot.acting = true;
  actions_.emplace_back([this, &robot, rule, hover_first, land, abort_with_safety_steps] {
    // Take the vehicle first (preempting whoever commands it), then stand
    // the mission down: the safety steps of an abort may need the lease.
    std::string lease_id;
    auto lease = takeLease(robot);
    if (lease.ok()) lease_id = lease->lease_id();
    if (hover_first && lease.ok()) {
      (void)robot.fc->executeFlightAction(lease_id, v1::FLIGHT_ACTION_HOVER);
    }
    if (!land) {
      // Hand the vehicle back hovering; the mission's safety steps (if any)
      // take it from here.
      if (lease.ok()) (void)robot.fc->releaseLease(lease_id);
      standDown(robot.robot_id, "safety: " + rule, abort_with_safety_steps);
    } else {
      // The stand-down goes on in the background: a system that does not
      // answer (a hung motion controller, whose calls run into their
      // deadline) must neither keep the vehicle in the air nor let the lease
      // taken above expire (the platform's own failsafe would then land it).
      // The vehicle lands once it has hovered `hover_before_land` and the
      // stand-down is done or has had its budget; the lease is renewed
      // meanwhile.
      auto stood_down = std::make_shared<bool>(false);  // guarded by mutex_
      {
        absl::MutexLock lock(&mutex_);
        if (stopping_) {
          *stood_down = true;
        } else {
          actions_.emplace_back(
              [this, stood_down, robot_id = robot.robot_id, rule, abort_with_safety_steps] {
                standDown(robot_id, "safety: " + rule, abort_with_safety_steps);
                absl::MutexLock lock(&mutex_);
                *stood_down = true;
              });
        }
      }
      // The hover is the vehicle's (its clock's time); the stand-down's
      // budget bounds calls (host time).
      const auto started = std::chrono::steady_clock::now();
      const auto stand_down_until = started + options_.stand_down_budget;
      auto renewed = started;
      const VehicleTimer hover(
          clock_, hover_first ? options_.hover_before_land : std::chrono::milliseconds(0));
      for (;;) {
        {
          absl::MutexLock lock(&mutex_);
          const auto now = std::chrono::steady_clock::now();
          if (stopping_ || (hover.done() && (*stood_down || now >= stand_down_until))) {
            if (!*stood_down && !stopping_) {
              std::fprintf(stderr,
                           "coordinator: safety: %s: the stand-down took longer than %lld ms: "
                           "landing meanwhile\n",
                           robot.robot_id.c_str(),
                           static_cast<long long>(options_.stand_down_budget.count()));
            }
            break;
          }
          // Until the stand-down is done, the stop, the next renewal or
          // the hover's end, whichever is first.
          const auto ended = [this, &stood_down]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
            return stopping_ || *stood_down;
          };
          mutex_.AwaitWithTimeout(absl::Condition(&ended),
                                  absl::FromChrono(hover.wallWait(kRenewPeriod)));
        }
        if (lease.ok() && std::chrono::steady_clock::now() - renewed >= kRenewPeriod) {
          (void)robot.fc->renewLease(lease_id);
          renewed = std::chrono::steady_clock::now();
        }
      }
      // Land under the lease kept alive above; take it again if it was lost
      // meanwhile, or if taking it did not answer in time (a loaded flight
      // controller may have granted it late).
      absl::StatusOr<v1::FlightState> landed =
          absl::FailedPreconditionError("the coordinator holds no lease");
      if (lease.ok()) landed = robot.fc->executeFlightAction(lease_id, v1::FLIGHT_ACTION_LAND);
      if (!landed.ok()) {
        lease = takeLease(robot);
        if (lease.ok()) {
          lease_id = lease->lease_id();
          landed = robot.fc->executeFlightAction(lease_id, v1::FLIGHT_ACTION_LAND);
        }
      }
      if (!lease.ok()) {
        std::fprintf(stderr, "coordinator: safety: %s: no lease (%s); EMERGENCY_LAND\n",
                     robot.robot_id.c_str(), std::string(lease.status().message()).c_str());
        (void)robot.fc->executeFlightAction("", v1::FLIGHT_ACTION_EMERGENCY_LAND);
      } else {
        if (!landed.ok()) {
          std::fprintf(stderr, "coordinator: safety: %s: LAND refused (%s); EMERGENCY_LAND\n",
                       robot.robot_id.c_str(), std::string(landed.status().message()).c_str());
          (void)robot.fc->executeFlightAction(lease_id, v1::FLIGHT_ACTION_EMERGENCY_LAND);
        }
        // Keep the lease alive until the vehicle is down (at most two
        // minutes of its time: a landing takes seconds).
        const VehicleTimer down(clock_, std::chrono::minutes(2));
        while (!down.done()) {
          auto status = robot.watcher->latest();
          if (status.ok() && !airborne(status->state()) &&
              status->state() != v1::FLIGHT_STATE_LANDING) {
            break;
          }
          if (!robot.fc->renewLease(lease_id).ok()) break;  // taken over, or gone
          absl::MutexLock lock(&mutex_);
          mutex_.AwaitWithTimeout(absl::Condition(&stopping_), absl::FromChrono(kRenewPeriod));
          if (stopping_) break;
        }
        (void)robot.fc->releaseLease(lease_id);
      }
    }
    absl::MutexLock lock(&mutex_);
    robot.acting = false;
  });
}

std::string SafetyController::standDown(const std::string& robot_id, const std::string& reason,
                                        bool run_safety_steps) {
  std::string done;
  if (auto mission = missions_.runningMissionOf(robot_id)) {
    auto aborted = missions_.abort(*mission, reason, run_safety_steps, robot_id);
    auto now = missions_.get(*mission);
    if (!aborted.ok() && now.ok() && now->state() == v1::MISSION_STATE_ABORTED) {
      done = absl::StrCat("; mission ", *mission, " aborted");  // by an earlier call
    } else if (!aborted.ok()) {
      done = absl::StrCat("; mission ", *mission, " not aborted: ", aborted.status().message());
    } else {
      done = absl::StrCat("; mission ", *mission, " aborted");
      // The runner looks at an abort between its waits: deactivating its
      // behavior before it has would end the mission FAILED on that step.
      const auto deadline = std::chrono::steady_clock::now() + options_.mission_ack_timeout;
      for (;;) {
        auto status = missions_.get(*mission);
        if (!status.ok() || status->state() == v1::MISSION_STATE_ABORTED ||
            status->state() == v1::MISSION_STATE_FAILED || status->has_end_time()) {
          break;
        }
        if (std::chrono::steady_clock::now() >= deadline) {
          absl::StrAppend(&done, " (its runner had not taken the abort within ",
                          options_.mission_ack_timeout.count(), " ms)");
          break;
        }
        absl::MutexLock lock(&mutex_);
        mutex_.AwaitWithTimeout(absl::Condition(&stopping_),
                                absl::FromChrono(std::chrono::milliseconds(5)));
        if (stopping_) break;
      }
    }
  }
  if (run_safety_steps) return done;  // the mission's safety steps command the vehicle
  int deactivated = 0;
  for (const auto& [behavior, activation] : fleet_.activeBehaviors(robot_id)) {
    const CatalogBehavior* entry = fleet_.catalog()->find(behavior);
    if (entry == nullptr) continue;
    bool commands = false;
    for (const auto& r : entry->holds)
      commands |= r == "platform_commands" || r == "motion_reference";
    if (!commands) continue;
    if (fleet_.deactivateBehavior(robot_id, behavior, activation).ok()) ++deactivated;
  }
  return absl::StrCat(done, "; ", deactivated, " commanding behaviors deactivated");
}

absl::StatusOr<v1::AcquireLeaseResponse> SafetyController::takeLease(Robot& robot) {
  std::set<std::string> controllers;
  for (const auto& [behavior, activation] : fleet_.activeBehaviors(robot.robot_id)) {
    const CatalogBehavior* entry = fleet_.catalog()->find(behavior);
    if (entry == nullptr) continue;
    for (const auto& cap : entry->provides) {
      if (cap == "motion_control") controllers.insert(activation);
    }
  }
  {
    absl::MutexLock lock(&mutex_);
    robot.preempted_controllers.insert(controllers.begin(), controllers.end());
  }
  return robot.fc->acquireLease(robot.robot_id + kSafetyHolderSuffix, kSafetyLeaseTtl,
                                /*preempt=*/true);
}

absl::StatusOr<std::string> SafetyController::flightAction(Robot& robot, int action, bool confirm) {
  const auto kind = static_cast<v1::FlightAction>(action);
  // The lease keeps a behavior still running from commanding meanwhile; the
  // platform accepts these actions without it.
  auto lease = takeLease(robot);
  const std::string lease_id = lease.ok() ? lease->lease_id() : "";
  auto state = robot.fc->executeFlightAction(lease_id, kind, 0.0, confirm);
  // Released at once: in EMERGENCY the platform takes no setpoint or action
  // but KILL, and a lease kept would refuse the next take-off.
  if (!lease_id.empty()) (void)robot.fc->releaseLease(lease_id);
  if (!state.ok()) return errors::withMetadata(state.status(), {{"robot", robot.robot_id}});
  return absl::StrCat(v1::FlightAction_Name(kind), " accepted by the flight controller at ",
                      robot.fc->address(), " (state ", v1::FlightState_Name(*state), ")");
}

absl::StatusOr<std::string> SafetyController::emergencyLand(const std::string& robot_id,
                                                            const std::string& reason) {
  Robot* robot = find(robot_id);
  if (robot == nullptr) return noFlightController(robot_id);
  // Stand down first, within the budget, then land whatever the stand-down
  // got done (it goes on in the background).
  struct StandDown {
    absl::Mutex mutex;
    bool done ABSL_GUARDED_BY(mutex) = false;
    std::string result ABSL_GUARDED_BY(mutex);
  };
  auto shared = std::make_shared<StandDown>();
  const std::string why = "emergency land" + (reason.empty() ? "" : ": " + reason);
  {
    absl::MutexLock lock(&mutex_);
    if (stopping_) {
      return errors::withReason(absl::UnavailableError("the coordinator is shutting down"),
                                v1::SHUTTING_DOWN);
    }
    fired_.push_back(robot_id + ": EmergencyLand requested: " + reason);
    countAction(robot_id, "emergency_land", "operator");
    actions_.emplace_back([this, shared, robot_id, why] {
      std::string result = standDown(robot_id, why, false);
      absl::MutexLock lock(&shared->mutex);
      shared->result = std::move(result);
      shared->done = true;
    });
  }
  std::string stood_down;
  {
    absl::MutexLock lock(&shared->mutex);
    shared->mutex.AwaitWithTimeout(absl::Condition(&shared->done),
                                   absl::FromChrono(options_.stand_down_budget));
    if (shared->done) {
      stood_down = shared->result;
    } else {
      stood_down = absl::StrCat("; standing down (mission abort, deactivations) took longer than ",
                                options_.stand_down_budget.count(), " ms: goes on meanwhile");
    }
  }
  auto done = flightAction(*robot, v1::FLIGHT_ACTION_EMERGENCY_LAND, false);
  if (!done.ok()) return done.status();
  return *done + stood_down;
}

absl::StatusOr<std::string> SafetyController::kill(const std::string& robot_id, bool confirm,
                                                   const std::string& reason) {
  if (!confirm) {
    return errors::withReason(
        absl::InvalidArgumentError(
            "Kill stops the motors and the vehicle falls: set confirm to true to do it"),
        v1::CONFIRMATION_REQUIRED, {{"robot", robot_id}});
  }
  Robot* robot = find(robot_id);
  if (robot == nullptr) return noFlightController(robot_id);
  const std::string why = "kill" + (reason.empty() ? "" : ": " + reason);
  // Motors off first; the mission is told at once (so that it ends ABORTED
  // for this reason), its behaviors are deactivated after.
  if (auto mission = missions_.runningMissionOf(robot_id)) {
    (void)missions_.abort(*mission, why, /*run_safety=*/false, robot_id);
  }
  auto done = flightAction(*robot, v1::FLIGHT_ACTION_KILL, true);
  if (!done.ok()) return done.status();
  {
    absl::MutexLock lock(&mutex_);
    fired_.push_back(robot_id + ": Kill requested: " + reason);
    countAction(robot_id, "kill", "operator");
  }
  return *done + standDown(robot_id, why, false);
}

}  // namespace behaviorlib::coordinator
