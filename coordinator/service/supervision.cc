#include "coordinator/service/supervision.h"

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
  if (stream_up_) return false;
  if (serving) {
    failing_since_.reset();
    return false;
  }
  if (!failing_since_) failing_since_ = now;
  if (down_ || now - *failing_since_ < grace_) return false;
  down_ = true;
  return true;
}

}  // namespace behaviorlib::coordinator
