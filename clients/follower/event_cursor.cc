#include "behaviorlib/follower/event_cursor.h"

namespace behaviorlib::follower {

namespace {
// Up to this many events in one WatchEvents message.
constexpr uint32_t kEventsPerMessage = 64;
}  // namespace

v1::WatchFleetEventsRequest EventCursor::request() const {
  v1::WatchFleetEventsRequest request;
  request.set_since_seq(since_seq_);
  request.set_incarnation(incarnation_);
  request.set_max_events_per_message(kEventsPerMessage);
  return request;
}

bool EventCursor::remember(const v1::FleetEvent& event) {
  if (event.kind_case() != v1::FleetEvent::kBehaviorEvent) return true;
  const v1::BehaviorEvent& e = event.behavior_event();
  const Identity identity = event.synthesized()
                                ? Identity{true, e.incarnation(), e.activation_id(), 0}
                                : Identity{false, e.incarnation(), std::string(), e.seq()};
  if (!seen_.insert(identity).second) return false;
  order_.push_back(identity);
  while (order_.size() > kRemembered) {
    seen_.erase(order_.front());
    order_.pop_front();
  }
  return true;
}

std::vector<v1::FleetEvent> EventCursor::accept(const v1::WatchFleetEventsResponse& response) {
  std::vector<v1::FleetEvent> fresh;
  auto take = [&](const v1::FleetEvent& event) {
    since_seq_ = event.seq();
    incarnation_ = event.incarnation();
    if (remember(event)) fresh.push_back(event);
  };
  switch (response.kind_case()) {
    case v1::WatchFleetEventsResponse::kStart: {
      const auto& start = response.start();
      if (!incarnation_.empty() && start.incarnation() != incarnation_) ++restarts_seen_;
      if (start.events_dropped()) dropped_count_ += start.dropped_count();
      incarnation_ = start.incarnation();
      break;
    }
    case v1::WatchFleetEventsResponse::kEvent:
      take(response.event());
      break;
    case v1::WatchFleetEventsResponse::kEvents:
      for (const auto& event : response.events().events()) take(event);
      break;
    case v1::WatchFleetEventsResponse::KIND_NOT_SET:
      break;
  }
  return fresh;
}

}  // namespace behaviorlib::follower
