#pragma once

// SensorStream: what the position estimators (ESTIMATE_POSITION_WITH_SENSOR,
// ESTIMATE_POSITION_WITH_LINEAR_SPEED) watch on each sensor topic they read:
// the stamp of its latest sample (stale stream) and whether its value keeps
// repeating (a frozen sensor publishing its last value with new stamps).
//
//   SensorStream gps("robots/drone1/gps", seconds(1), milliseconds(500));
//   gps.add(stamp, value_vector);                  // every sample (under the caller's lock)
//   if (auto problem = gps.problem(now(), activated_at)) -> PROCESS_FAILURE(*problem)
//
// freshSampleProblem() is the before-activation check of checkSituation: is
// there a recent sample on the topic at all.

#include <Eigen/Core>
#include <optional>
#include <string>

#include "behaviorlib/basic_quadrotor_behaviors/position_estimators.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::basic {

/// "robots/{robot_id}/{name}".
inline std::string sensorTopic(const std::string& robot_id, const std::string& name) {
  return "robots/" + robot_id + "/" + name;
}

/// Seconds since the clock's epoch (the filters' time base).
inline double toSeconds(TimePoint t) {
  return std::chrono::duration<double>(t.time_since_epoch()).count();
}

class SensorStream {
 public:
  /// `timeout`: a sample older than this (behavior clock) is stale.
  /// `frozen_timeout`: the same value repeated over longer than this is a
  /// frozen sensor; zero turns the check off (a noiseless simulated sensor
  /// repeats its value legitimately).
  SensorStream(std::string topic, Duration timeout, Duration frozen_timeout)
      : topic_(std::move(topic)), timeout_(timeout), frozen_timeout_(frozen_timeout) {}

  void reset() {
    last_.reset();
    frozen_.reset();
  }
  void add(TimePoint stamp, const Eigen::VectorXd& value) {
    if (!last_ || stamp > *last_) last_ = stamp;
    frozen_.add(toSeconds(stamp), value);
  }
  /// The stream's problem at `now` for an estimator activated at
  /// `activated_at`: no sample within the timeout of the activation, the
  /// latest sample older than the timeout, or a frozen value. nullopt when
  /// all is well.
  std::optional<std::string> problem(TimePoint now, TimePoint activated_at) const;

  const std::string& topic() const { return topic_; }
  std::optional<TimePoint> last() const { return last_; }

 private:
  std::string topic_;
  Duration timeout_;
  Duration frozen_timeout_;
  std::optional<TimePoint> last_;
  FrozenDetector frozen_;
};

inline Eigen::Vector3d toEigen(const v1::Vector3& v) { return {v.x(), v.y(), v.z()}; }

/// A message's quaternion, normalised; nullopt when it is not finite or far
/// from unit length (not an orientation).
inline std::optional<Eigen::Quaterniond> toOrientation(const v1::Quaternion& q) {
  const Eigen::Quaterniond e(q.w(), q.x(), q.y(), q.z());
  const double norm = e.norm();
  if (!(norm > 0.5 && norm < 1.5)) return std::nullopt;
  return e.normalized();
}

/// checkSituation() before activation: a sample of type T on `topic` no
/// older than `limit` at `now`. The problem as a reason with its code, or
/// nullopt.
template <class T>
std::optional<flight::SituationProblem> freshSampleProblem(channel::ChannelClient& channel,
                                                           const std::string& topic, TimePoint now,
                                                           Duration limit) {
  auto sample = channel.getLatest(topic, std::chrono::milliseconds(300));
  if (!sample.ok()) {
    if (sample.status().code() == absl::StatusCode::kNotFound) {
      return flight::SituationProblem{
          v1::SITUATION_REASON_INPUT_MISSING,
          "nothing on " + topic + ": is the simulator (or the sensor driver) publishing?"};
    }
    return flight::SituationProblem{v1::SITUATION_REASON_PLATFORM_UNAVAILABLE,
                                    "cannot read " + topic + " from the channel at " +
                                        channel.address() + ": " +
                                        std::string(sample.status().message())};
  }
  T message;
  if (!sample->sample().UnpackTo(&message)) {
    return flight::SituationProblem{v1::SITUATION_REASON_INPUT_INVALID,
                                    topic + " does not carry " + T::descriptor()->full_name()};
  }
  if (auto stale = flight::staleness([&] { return "the latest sample on " + topic; },
                                     message.header(), now, limit)) {
    return flight::SituationProblem{v1::SITUATION_REASON_INPUT_STALE, *stale};
  }
  return std::nullopt;
}

}  // namespace behaviorlib::basic
