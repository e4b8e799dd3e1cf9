#pragma once

// The console's live feed: a bounded broadcast of Server-Sent Events. Every
// message gets the next sequence number (its SSE id). Events (publish) are
// kept, the last `capacity` of them, so a browser that reconnects with
// Last-Event-ID gets what it missed, and a new one the recent past. States
// (publishLatest: a vehicle's pose, the coordinator's reachability) keep
// only their latest message per key, so a flood of samples never pushes the
// events out. Thread-safe.

#include <chrono>
#include <cstdint>
#include <deque>
#include <map>
#include <string>
#include <vector>

#include "absl/synchronization/mutex.h"

namespace behaviorlib::console {

class EventHub {
 public:
  struct Message {
    uint64_t id = 0;
    std::string event;  ///< the SSE event type: fleet, mission, ...
    std::string data;   ///< one line of JSON
  };

  /// Keeps the last `capacity` events and at most `max_states` states (the
  /// oldest state goes first).
  explicit EventHub(size_t capacity, size_t max_states = 10000)
      : capacity_(capacity), max_states_(max_states) {}

  /// Adds an event; returns its id.
  uint64_t publish(std::string event, std::string data);
  /// Replaces the state `key`'s message; returns its id.
  uint64_t publishLatest(const std::string& key, std::string event, std::string data);

  /// The kept messages after `after`, in id order, waiting up to `wait` for
  /// one. Empty when the wait ended without one, or the hub is closed.
  std::vector<Message> after(uint64_t after, std::chrono::milliseconds wait);

  /// Wakes every waiter; after() returns at once from now on.
  void close();
  bool closed() const;
  uint64_t lastId() const;

  /// One message as the SSE wire format: "id: N\nevent: E\ndata: D\n\n".
  static std::string format(const Message& message);

 private:
  const size_t capacity_;
  const size_t max_states_;
  mutable absl::Mutex mutex_;
  std::deque<Message> kept_ ABSL_GUARDED_BY(mutex_);
  std::map<std::string, Message> latest_ ABSL_GUARDED_BY(mutex_);
  uint64_t last_id_ ABSL_GUARDED_BY(mutex_) = 0;
  bool closed_ ABSL_GUARDED_BY(mutex_) = false;
};

}  // namespace behaviorlib::console
