#include "behaviorlib/console/event_hub.h"

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "absl/time/time.h"

namespace behaviorlib::console {

uint64_t EventHub::publish(std::string event, std::string data) {
  absl::MutexLock lock(&mutex_);
  Message message;
  message.id = ++last_id_;
  message.event = std::move(event);
  message.data = std::move(data);
  kept_.push_back(std::move(message));
  while (kept_.size() > capacity_) kept_.pop_front();
  return last_id_;
}

uint64_t EventHub::publishLatest(const std::string& key, std::string event, std::string data) {
  absl::MutexLock lock(&mutex_);
  Message& message = latest_[key];
  message.id = ++last_id_;
  message.event = std::move(event);
  message.data = std::move(data);
  if (latest_.size() > max_states_) {
    latest_.erase(
        std::min_element(latest_.begin(), latest_.end(),
                         [](const auto& a, const auto& b) { return a.second.id < b.second.id; }));
  }
  return last_id_;
}

std::vector<EventHub::Message> EventHub::after(uint64_t after, std::chrono::milliseconds wait) {
  absl::MutexLock lock(&mutex_);
  auto ready = [this, after]()
                   ABSL_SHARED_LOCKS_REQUIRED(mutex_) { return closed_ || last_id_ > after; };
  mutex_.AwaitWithTimeout(absl::Condition(&ready), absl::FromChrono(wait));
  std::vector<Message> out;
  if (closed_) return out;
  for (const auto& message : kept_) {
    if (message.id > after) out.push_back(message);
  }
  for (const auto& [key, message] : latest_) {
    if (message.id > after) out.push_back(message);
  }
  std::sort(out.begin(), out.end(), [](const Message& a, const Message& b) { return a.id < b.id; });
  return out;
}

void EventHub::close() {
  absl::MutexLock lock(&mutex_);
  closed_ = true;
}

bool EventHub::closed() const {
  absl::MutexLock lock(&mutex_);
  return closed_;
}

uint64_t EventHub::lastId() const {
  absl::MutexLock lock(&mutex_);
  return last_id_;
}

std::string EventHub::format(const Message& message) {
  return absl::StrCat("id: ", message.id, "\nevent: ", message.event, "\ndata: ", message.data,
                      "\n\n");
}

}  // namespace behaviorlib::console
