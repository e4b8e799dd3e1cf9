#pragma once

// Follows what the fleet does, as a client of the coordinator and the data
// channel, and hands it to a sink: the console's gateway (to browsers) and
// the flight recorder (to a file) are its two sinks.
//
// - events: the coordinator's WatchEvents, resumed without gaps or
//   duplicates (EventCursor);
// - missions: each change of a mission's status (ListMissions every
//   mission_poll, or at once after kick(), and a WatchMission per running
//   mission);
// - beliefs: every belief write (WatchBeliefs, resumed after the last
//   version seen);
// - samples: the vehicle topics of every robot of the fleet (ListSystems
//   finds them), throttled or every one;
// - whether the coordinator is reachable.
//
// Every stream is opened again after it ends, with a delay that doubles up
// to 2 s, until shutdown().

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "absl/synchronization/mutex.h"
#include "behaviorlib/v1/channel.grpc.pb.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"

namespace behaviorlib::follower {

class FleetSink {
 public:
  virtual ~FleetSink() = default;
  /// Called from the follower's threads, each kind from one thread at a
  /// time; samples of different topics from different threads at once.
  virtual void onEvent(const v1::FleetEvent& event) = 0;
  /// A mission whose status changed (or was seen for the first time).
  virtual void onMission(const v1::MissionStatus& status) = 0;
  virtual void onBelief(const v1::Belief& belief) = 0;
  virtual void onSample(const v1::SubscribeResponse& sample) = 0;
  /// The coordinator became reachable or not (once per change).
  virtual void onCoordinator(bool up, const std::string& why) = 0;
};

struct FollowerOptions {
  /// Deadline of a unary coordinator call.
  std::chrono::milliseconds call_timeout{10000};
  /// How often the mission list is read to find missions to watch.
  std::chrono::milliseconds mission_poll{1000};
  /// Missions watched at once (the running and paused ones).
  size_t max_watched_missions = 16;
  /// The data channel, for the vehicle topics (none: no samples).
  std::shared_ptr<grpc::Channel> data_channel;
  /// The topics followed for each robot of the fleet, under robots/{id}/,
  /// each with the rate it is read at: at most max_rate_hz samples a second
  /// of wall time, the newest (SubscribeRequest.max_rate_hz, which the
  /// broker and the simulator honour); 0: every sample (a queue of
  /// sample_queue per topic), unless vehicle_period says otherwise.
  struct VehicleTopic {
    std::string name;
    double max_rate_hz = 0;
  };
  std::vector<VehicleTopic> vehicle_topics;
  /// For a topic read at every sample (max_rate_hz 0): at most one sample
  /// per robot this often, the latest, kept here (zero: every sample).
  std::chrono::milliseconds vehicle_period{100};
  uint32_t sample_queue = 1000;
  /// Robots whose vehicle topics are followed.
  size_t max_robots = 16;
};

class FleetFollower {
 public:
  FleetFollower(std::shared_ptr<grpc::Channel> coordinator, FollowerOptions options,
                FleetSink* sink);
  /// Stops everything (shutdown()).
  ~FleetFollower();
  FleetFollower(const FleetFollower&) = delete;
  FleetFollower& operator=(const FleetFollower&) = delete;

  void start();
  /// Ends every stream and joins the threads; the sink is called no more.
  void shutdown();
  /// Reads the mission list now (a mission was started or controlled).
  void kick();
  /// Brings the sink up to the coordinator's present, before a stop: every
  /// listed mission's current status (one ListMissions, handed on when it
  /// changed), and every event up to the newest one the coordinator holds
  /// now (the events stream delivers them; this waits for it). False when
  /// the coordinator did not answer or `timeout` passed first (at once for a
  /// timeout of zero: no catch-up).
  bool catchUp(std::chrono::milliseconds timeout);

 private:
  template <typename Response, typename Open, typename Handle, typename Ended>
  void followStream(const std::string& key, Open open, Handle handle, Ended ended);
  void followEvents();
  void followMissions();
  void watchMission(const std::string& mission_id);
  void changedMission(const v1::MissionStatus& status);
  void followRobots();
  void followBeliefs();
  void followTopic(const std::string& topic, double max_rate_hz);
  void setCoordinatorUp(bool up, const std::string& why);
  // Waits `wait`, or until kick() if kickable; false once stopping.
  bool sleepFor(std::chrono::milliseconds wait, bool kickable);

  const std::unique_ptr<v1::Coordinator::Stub> stub_;
  const FollowerOptions options_;
  FleetSink* const sink_;
  std::unique_ptr<v1::DataChannel::Stub> data_;
  std::thread events_thread_;
  std::thread missions_thread_;
  std::thread beliefs_thread_;

  absl::Mutex mutex_;
  bool started_ ABSL_GUARDED_BY(mutex_) = false;
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  bool kicked_ ABSL_GUARDED_BY(mutex_) = false;
  bool coordinator_up_ ABSL_GUARDED_BY(mutex_) = false;
  bool coordinator_known_ ABSL_GUARDED_BY(mutex_) = false;
  // The calls to cancel at shutdown: the streams and mission watches.
  std::map<std::string, grpc::ClientContext*> streams_ ABSL_GUARDED_BY(mutex_);
  std::map<std::string, std::thread> mission_watchers_ ABSL_GUARDED_BY(mutex_);
  // Watchers whose mission ended, to join.
  std::vector<std::string> finished_watchers_ ABSL_GUARDED_BY(mutex_);
  // The robots whose vehicle topics are followed, and their threads.
  std::set<std::string> robots_ ABSL_GUARDED_BY(mutex_);
  std::vector<std::thread> topic_threads_ ABSL_GUARDED_BY(mutex_);
  // Where the events stream is: the last coordinator seq handed to the
  // sink, of this incarnation.
  uint64_t events_seq_ ABSL_GUARDED_BY(mutex_) = 0;
  std::string events_incarnation_ ABSL_GUARDED_BY(mutex_);
  // The last status seen of each mission (serialized).
  std::map<std::string, std::string> missions_ ABSL_GUARDED_BY(mutex_);
};

}  // namespace behaviorlib::follower
