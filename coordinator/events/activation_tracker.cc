#include "coordinator/events/activation_tracker.h"

#include <utility>

namespace behaviorlib::coordinator {

namespace {

void setTimestamp(google::protobuf::Timestamp* timestamp,
                  std::chrono::system_clock::time_point time) {
  const auto since_epoch =
      std::chrono::duration_cast<std::chrono::nanoseconds>(time.time_since_epoch());
  const auto seconds = std::chrono::floor<std::chrono::seconds>(since_epoch);
  timestamp->set_seconds(seconds.count());
  timestamp->set_nanos(static_cast<int32_t>((since_epoch - seconds).count()));
}

}  // namespace

ActivationTracker::ActivationTracker(std::string robot_id, std::string system)
    : robot_id_(std::move(robot_id)), system_(std::move(system)) {}

void ActivationTracker::startIncarnation(const std::string& incarnation) {
  if (incarnation == incarnation_) return;
  incarnation_ = incarnation;
  last_seq_ = 0;
  active_.clear();
  fenced_running_.clear();
  fenced_.clear();
}

ActivationTracker::Verdict ActivationTracker::accept(const v1::BehaviorEvent& event) {
  if (event.incarnation() != incarnation_ || event.seq() <= last_seq_) return Verdict::kDuplicate;
  last_seq_ = event.seq();

  const std::string& id = event.activation_id();
  if (!id.empty() && fenced_.contains(id)) {
    if (event.has_finished()) fenced_running_.erase(id);
    return Verdict::kFenced;
  }

  auto it = active_.find(event.behavior());
  switch (event.kind_case()) {
    case v1::BehaviorEvent::kActivated: {
      Activation& a = active_[event.behavior()];
      a.behavior = event.behavior();
      a.activation_id = id;
      a.state = v1::BEHAVIOR_STATE_ACTIVE;
      a.parameters = event.activated().parameters();
      break;
    }
    case v1::BehaviorEvent::kFinished:
      if (it != active_.end() && it->second.activation_id == id) active_.erase(it);
      break;
    case v1::BehaviorEvent::kPaused:
      if (it != active_.end() && it->second.activation_id == id) {
        it->second.state = v1::BEHAVIOR_STATE_PAUSED;
      }
      break;
    case v1::BehaviorEvent::kResumed:
      if (it != active_.end() && it->second.activation_id == id) {
        it->second.state = v1::BEHAVIOR_STATE_ACTIVE;
      }
      break;
    case v1::BehaviorEvent::kModified:
      if (it != active_.end() && it->second.activation_id == id) {
        it->second.parameters = event.modified().parameters();
      }
      break;
    default:
      break;
  }
  return Verdict::kForward;
}

std::vector<v1::BehaviorEvent> ActivationTracker::finishAll(
    const std::string& message, std::chrono::system_clock::time_point now, bool fence) {
  std::vector<v1::BehaviorEvent> out;
  for (auto& [behavior, activation] : active_) {
    v1::BehaviorEvent event;
    event.set_incarnation(incarnation_);
    event.set_robot_id(robot_id_);
    event.set_system(system_);
    event.set_behavior(behavior);
    event.set_activation_id(activation.activation_id);
    setTimestamp(event.mutable_wall_time(), now);
    auto* finished = event.mutable_finished();
    finished->set_cause(v1::TERMINATION_CAUSE_PROCESS_FAILURE);
    finished->set_message(message);
    *finished->mutable_parameters() = activation.parameters;
    out.push_back(std::move(event));
    if (fence) {
      fenced_.insert(activation.activation_id);
      fenced_running_[activation.activation_id] = std::move(activation);
    }
  }
  active_.clear();
  return out;
}

std::vector<ActivationTracker::Activation> ActivationTracker::fencedStillRunning() const {
  std::vector<Activation> out;
  for (const auto& [id, activation] : fenced_running_) out.push_back(activation);
  return out;
}

}  // namespace behaviorlib::coordinator
