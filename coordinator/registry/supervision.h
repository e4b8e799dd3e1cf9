#pragma once

// When is a behavior system down? When its event stream broke and its gRPC
// health check has been failing for longer than a grace period (wall time).
// A frozen process (SIGSTOP, a deadlock) keeps its connection and so its
// stream open: while the stream is up the link still probes health when the
// stream is silent or heartbeats stopped, and once those probes have failed
// for the grace period (unanswered()) it breaks the stream itself; the first
// failed check after that declares the system down.
// A pure state machine: the intake thread feeds it what happened and when;
// unit tests feed it a fake time.
//
//   Supervision supervision(std::chrono::seconds(1));
//   supervision.streamBroken(now);
//   if (supervision.healthChecked(/*serving=*/false, now)) declareDown();
//   supervision.streamUp();   // reconnected: healthy again

#include <chrono>
#include <optional>

namespace behaviorlib::coordinator {

class Supervision {
 public:
  using TimePoint = std::chrono::steady_clock::time_point;

  explicit Supervision(std::chrono::nanoseconds grace) : grace_(grace) {}

  /// The event stream is established: the system is healthy, and a later
  /// outage is a new one.
  void streamUp();
  /// The event stream broke (or could not be opened) at `now`.
  void streamBroken(TimePoint now);
  /// A health check answered at `now`; `serving` is true for SERVING. Returns
  /// true exactly once per outage: when the stream is broken and the check
  /// has been failing for at least the grace period. Checks while the stream
  /// is up never return true, but a failing window they start is kept when
  /// the stream breaks.
  bool healthChecked(bool serving, TimePoint now);
  /// The stream is up but the health check has been failing for at least the
  /// grace period at `now`: the process stopped answering (frozen) while its
  /// connection stays open.
  bool unanswered(TimePoint now) const;

  bool streamIsUp() const { return stream_up_; }
  /// True once declared down, until the stream is up again.
  bool down() const { return down_; }
  /// Since when the health check has been failing, if it is.
  std::optional<TimePoint> failingSince() const { return failing_since_; }
  std::chrono::nanoseconds grace() const { return grace_; }

 private:
  std::chrono::nanoseconds grace_;
  bool stream_up_ = false;
  bool down_ = false;
  std::optional<TimePoint> failing_since_;
};

}  // namespace behaviorlib::coordinator
