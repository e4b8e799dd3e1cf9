#pragma once

// Follows one behavior system's event stream for the coordinator: drops what
// it has already seen (resumed streams replay from since_seq), remembers the
// activations in progress, and makes the finished events that a system which
// went down or restarted can no longer send, so that every activation ends
// with exactly one finished event in the coordinator's stream.
//
//   ActivationTracker tracker("drone1", "basic_quadrotor_behaviors");
//   tracker.startIncarnation(start.incarnation());      // first contact
//   if (tracker.accept(event) == Verdict::kForward) log.append(...);
//   // the stream broke and the health check kept failing:
//   for (auto& e : tracker.finishAll(cause_message, now, /*fence=*/true)) log.append(...);
//
// A fenced activation was reported finished by the coordinator while its
// system was unreachable. If the same incarnation comes back, the system's
// later events of that activation are dropped, and fencedStillRunning() lists
// the ones to deactivate there once the replay is through.
//
// Not thread-safe: one intake thread owns it (callers lock around readers).

#include <chrono>
#include <cstdint>
#include <map>
#include <set>
#include <string>
#include <vector>

#include "behaviorlib/v1/behavior.pb.h"

namespace behaviorlib::coordinator {

class ActivationTracker {
 public:
  enum class Verdict {
    /// New: forward it to the coordinator's stream.
    kForward,
    /// Already seen (seq not after the last one), or of another incarnation.
    kDuplicate,
    /// Belongs to an activation the coordinator already finished.
    kFenced,
  };

  /// An activation in progress, as known from the events.
  struct Activation {
    std::string behavior;
    std::string activation_id;
    /// ACTIVE or PAUSED.
    v1::BehaviorState state = v1::BEHAVIOR_STATE_ACTIVE;
    /// The parameters in effect (from the activated or last modified event).
    google::protobuf::Struct parameters;
  };

  ActivationTracker(std::string robot_id, std::string system);

  /// Sets the system name once learned (systems from the --systems file).
  void setSystem(std::string system) { system_ = std::move(system); }

  /// The incarnation whose events are followed (empty before the first).
  const std::string& incarnation() const { return incarnation_; }
  /// Seq of the newest event seen from it (the since_seq to resume from).
  uint64_t lastSeq() const { return last_seq_; }

  /// Follows a new incarnation from its first event: forgets the previous
  /// one's activations (call finishAll first) and fenced ids.
  void startIncarnation(const std::string& incarnation);

  /// Classifies one event of the stream and updates the activations.
  Verdict accept(const v1::BehaviorEvent& event);

  /// Ends every activation in progress: one synthesized finished event each
  /// (cause PROCESS_FAILURE, `message`, the activation's parameters, seq 0,
  /// wall_time `now`), in behavior-name order. With `fence`, their later
  /// events from the same incarnation are dropped (see fencedStillRunning).
  std::vector<v1::BehaviorEvent> finishAll(const std::string& message,
                                           std::chrono::system_clock::time_point now, bool fence);

  /// Fenced activations whose finished event has not arrived: still running
  /// on the system although the coordinator reported them finished.
  std::vector<Activation> fencedStillRunning() const;

  /// Activations in progress, by behavior name.
  const std::map<std::string, Activation>& active() const { return active_; }

 private:
  std::string robot_id_;
  std::string system_;
  std::string incarnation_;
  uint64_t last_seq_ = 0;
  std::map<std::string, Activation> active_;  // by behavior
  // Fenced activation ids -> their activation, while no finished event of
  // theirs arrived.
  std::map<std::string, Activation> fenced_running_;
  // Every fenced activation id of this incarnation.
  std::set<std::string> fenced_;
};

}  // namespace behaviorlib::coordinator
