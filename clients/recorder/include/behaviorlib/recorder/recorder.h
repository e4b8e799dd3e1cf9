#pragma once

// The flight recorder (decision 36): what the fleet does, into an MCAP file
// with protobuf schemas, as `behaviorctl record` and the launcher's --record
// run it.
//
// MCAP topics (each a channel with the message's protobuf schema):
//   coordinator/events    behaviorlib.v1.FleetEvent, every event of the
//                         coordinator's WatchEvents (no gap, no duplicate)
//   coordinator/missions  behaviorlib.v1.MissionStatus, each change
//   coordinator/beliefs   behaviorlib.v1.Belief, each write
//   robots/{id}/{topic}   the data channel's samples of the chosen topics of
//                         every robot, every one or at the topic's chosen
//                         rate (the broker's max_rate_hz), with the type
//
// log_time is when the recorder received the message (the injected clock);
// publish_time is the source's own stamp: the broker's receive time of a
// sample, the coordinator's time of an event, a belief's write time, and
// the log time for a mission status.

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/follower/fleet_follower.h"
#include "formats/mcap/mcap.h"

namespace behaviorlib::recorder {

inline constexpr char kEventsTopic[] = "coordinator/events";
inline constexpr char kMissionsTopic[] = "coordinator/missions";
inline constexpr char kBeliefsTopic[] = "coordinator/beliefs";
inline constexpr char kProfile[] = "behaviorlib";

/// The vehicle topics recorded by default: poses and velocity at 30 samples
/// a second of wall time ("name@HZ", see parseTopic), the flight state,
/// marker detections and the map at every sample; camera and lidar only on
/// request (they are large).
std::vector<std::string> defaultTopics();

/// One recorded vehicle topic, "name" (every sample) or "name@HZ" (at most
/// HZ samples a second of wall time, the newest each time and always the
/// last: SubscribeRequest.max_rate_hz). INVALID_ARGUMENT names the entry
/// when the name is not a topic segment path or the rate is not a number in
/// (0, 100000].
absl::StatusOr<follower::FollowerOptions::VehicleTopic> parseTopic(const std::string& entry);

/// Serialized google.protobuf.FileDescriptorSet of `type` and every file it
/// imports, dependencies first (an MCAP "protobuf" schema), from the
/// descriptors of every behaviorlib proto; NOT_FOUND for another type.
absl::StatusOr<std::string> schemaOf(const std::string& type);

struct RecorderOptions {
  std::string path;
  /// The data channel; none: no samples are recorded.
  std::shared_ptr<grpc::Channel> data_channel;
  /// Vehicle topics under robots/{id}/, each "name" or "name@HZ"
  /// (parseTopic; start() refuses a bad one).
  std::vector<std::string> topics = defaultTopics();
  /// Nanoseconds since the Unix epoch (tests give a fake clock).
  std::function<uint64_t()> now_ns;
  /// The file stops growing past this size (what came later is counted as
  /// dropped).
  uint64_t max_bytes = uint64_t{4} << 30;
  /// Robots whose topics are recorded.
  size_t max_robots = 16;
  /// How often the mission list is read, and how many missions are
  /// watched at once (FollowerOptions).
  std::chrono::milliseconds mission_poll{1000};
  size_t max_watched_missions = 16;
  /// stop() first catches up with the coordinator (FleetFollower::catchUp):
  /// every mission's last status and every event it holds, for at most
  /// this long (zero: not at all).
  std::chrono::milliseconds drain_timeout{5000};
};

struct RecorderStats {
  std::map<std::string, uint64_t> messages;  // per MCAP topic
  /// Messages not recorded: past max_bytes, or lost by the broker's queue
  /// of a subscription that fell behind.
  uint64_t dropped = 0;
  uint64_t bytes = 0;
  /// stop() caught up with the coordinator before closing the file.
  bool drained = false;
};

class Recorder : private follower::FleetSink {
 public:
  /// Creates the file (an error names it) and follows the coordinator.
  static absl::StatusOr<std::unique_ptr<Recorder>> start(std::shared_ptr<grpc::Channel> coordinator,
                                                         RecorderOptions options);
  ~Recorder() override;
  Recorder(const Recorder&) = delete;
  Recorder& operator=(const Recorder&) = delete;

  /// Hands what is recorded to the operating system (a killed recorder's
  /// file reads up to its last flush).
  absl::Status flush();
  /// Catches up with the coordinator (at most drain_timeout; stats().drained
  /// says whether it did), stops following and closes the file with its
  /// summary.
  absl::Status stop();
  RecorderStats stats();

 private:
  Recorder(std::shared_ptr<grpc::Channel> coordinator, RecorderOptions options,
           std::unique_ptr<mcap::Writer> writer);
  void onEvent(const v1::FleetEvent& event) override;
  void onMission(const v1::MissionStatus& status) override;
  void onBelief(const v1::Belief& belief) override;
  void onSample(const v1::SubscribeResponse& sample) override;
  void onCoordinator(bool up, const std::string& why) override;
  void record(const std::string& topic, const std::string& type, const std::string& data,
              uint64_t publish_time_ns);

  const RecorderOptions options_;
  absl::Mutex mutex_;
  std::unique_ptr<mcap::Writer> writer_ ABSL_GUARDED_BY(mutex_);
  RecorderStats stats_ ABSL_GUARDED_BY(mutex_);
  std::map<std::string, uint16_t> channels_ ABSL_GUARDED_BY(mutex_);
  // Per topic, the dropped_count of the subscription's last sample.
  std::map<std::string, uint64_t> broker_drops_ ABSL_GUARDED_BY(mutex_);
  bool stopped_ ABSL_GUARDED_BY(mutex_) = false;
  follower::FleetFollower follower_;
};

struct ReplayOptions {
  /// 1: as recorded; 2: twice as fast; 0: as fast as the broker takes them.
  double speed = 1;
  /// Only MCAP topics with this prefix (empty: all).
  std::string topic_prefix;
  /// Waits until a time on the recording's timeline has come (tests give a
  /// fake one); the default sleeps on the host's steady clock.
  std::function<void(uint64_t offset_ns)> wait_until;
};

struct ReplayStats {
  uint64_t published = 0;
  uint64_t skipped = 0;                    // messages of topics the broker cannot carry
  std::map<std::string, uint64_t> topics;  // per broker topic
  bool complete = false;                   // the recording ended with its summary
};

/// The broker topic a recorded message is published on: a sample's own
/// topic; a coordinator message's robot's `recording/events`,
/// `recording/missions` or `recording/beliefs` (a belief's robot is its
/// key's first segment). Empty when it has none.
std::string replayTopic(const std::string& mcap_topic, const std::string& type,
                        const std::string& data);

/// Publishes a recording into a broker, in order, paced by log time.
absl::StatusOr<ReplayStats> replay(const std::string& path, v1::DataChannel::StubInterface* broker,
                                   const ReplayOptions& options);

}  // namespace behaviorlib::recorder
