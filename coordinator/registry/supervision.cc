#include "coordinator/registry/supervision.h"

namespace behaviorlib::coordinator {

void Supervision::streamUp() {
  stream_up_ = true;
  down_ = false;
  failing_since_.reset();
}

void Supervision::streamBroken(TimePoint /*now*/) {
  // The failing window starts with the first failed health check, not with
  // the break: a stream may end for reasons of its own (a slow reader cut
  // off, an orderly restart of the stream) while the process is fine.
  stream_up_ = false;
}

bool Supervision::healthChecked(bool serving, TimePoint now) {
  if (serving) {
    failing_since_.reset();
    return false;
  }
  if (!failing_since_) failing_since_ = now;
  // While the stream is up only unanswered() acts on the failing window.
  if (stream_up_ || down_ || now - *failing_since_ < grace_) return false;
  down_ = true;
  return true;
}

bool Supervision::unanswered(TimePoint now) const {
  return stream_up_ && !down_ && failing_since_ && now - *failing_since_ >= grace_;
}

}  // namespace behaviorlib::coordinator
