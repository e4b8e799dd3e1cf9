#pragma once

// LinkLossWatch: what a behavior system does on its own when the vehicle
// loses its link to the ground (decision 39). A mission runs on the ground:
// once the coordinator has been unreachable for `timeout` on the system's
// clock (the vehicle's time), nothing can end the behaviors the mission
// started or start the next step. The system then activates `action` (LAND,
// with the parameters' defaults), as an autopilot's data-link-loss failsafe
// would, and retries it every second while it is refused (another holder's
// lease), until it is accepted or the link returns. Once the coordinator
// accepts the registration again, the watch is ready for the next loss.
//
//   LinkLossWatch watch({.timeout = seconds(10), .action = "LAND"}, clock,
//                       [&] { return registration.registered(); }, host, "basic");

#include <chrono>
#include <functional>
#include <optional>
#include <string>
#include <thread>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/behavior_host.h"
#include "behaviorlib/clock.h"

namespace behaviorlib::server {

struct LinkLossOptions {
  /// How long the coordinator may be unreachable (zero: never act).
  Duration timeout{0};
  /// The behavior of this system to activate then (empty: none).
  std::string action;
};

class LinkLossWatch {
 public:
  /// `registered` says whether the coordinator accepts the registration now.
  LinkLossWatch(LinkLossOptions options, const Clock& clock, std::function<bool()> registered,
                BehaviorHost& host, std::string log_prefix);
  /// Stops the watch (an activation under way is left to the host).
  ~LinkLossWatch();
  LinkLossWatch(const LinkLossWatch&) = delete;
  LinkLossWatch& operator=(const LinkLossWatch&) = delete;

  /// Times the action was activated so far.
  int actedCount() const;

 private:
  void run();
  void act();

  const LinkLossOptions options_;
  const Clock& clock_;
  const std::function<bool()> registered_;
  BehaviorHost& host_;
  const std::string log_prefix_;

  mutable absl::Mutex mutex_;
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  bool acted_ ABSL_GUARDED_BY(mutex_) = false;  // in this loss
  bool activating_ ABSL_GUARDED_BY(mutex_) = false;
  int acted_count_ ABSL_GUARDED_BY(mutex_) = 0;
  bool told_refusal_ ABSL_GUARDED_BY(mutex_) = false;
  std::thread thread_;
};

}  // namespace behaviorlib::server
