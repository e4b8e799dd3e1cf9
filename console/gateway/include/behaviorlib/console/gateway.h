#pragma once

// The console's gateway: the browser cannot speak gRPC, so this small HTTP
// server does, like any other client of the coordinator (decision 35).
//
//   GET  /                      the console's page and its scripts (--web-dir)
//   GET  /healthz               200 once serving
//   GET  /api/world             the map's world (--world), boxes and markers
//   GET  /api/events            Server-Sent Events: `fleet` (every FleetEvent
//                               of the coordinator's WatchEvents, resumed
//                               without gaps or duplicates), `mission` (each
//                               mission status change), `vehicle` (each
//                               robot's pose and flight status from the data
//                               channel, at most vehicle_period apart per
//                               topic), `belief` (each belief's latest
//                               value: the markers found, ...), `gateway`
//                               (whether the coordinator is reachable)
//   GET  /api/recordings        the flight recordings (*.mcap) of
//                               recordings_dir: {"recordings": [{name, bytes}]}
//   GET  /api/recordings/NAME   one recording as the feed's messages, for the
//                               page to scrub through: {name, complete,
//                               duration_ms, truncated, messages: [{t_ms,
//                               event, data}]} (vehicle samples at most one
//                               per recording_sample_period per topic)
//   POST /api/coordinator/NAME  one unary Coordinator call of the console's
//                               (the request as JSON, proto field names; the
//                               response as JSON), e.g. ListSystems,
//                               StartMission, CheckMission, AbortMission,
//                               EmergencyLand
//
// An `Authorization` header is passed on to the coordinator, so the roles of
// its access policy apply to the browser's calls. A refused call answers the
// HTTP status of its gRPC code with the google.rpc.Status as JSON.

#include <grpcpp/grpcpp.h>

#include <atomic>
#include <chrono>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/status.h"
#include "behaviorlib/console/event_hub.h"
#include "behaviorlib/follower/fleet_follower.h"
#include "behaviorlib/server_kit/confined_files.h"
#include "behaviorlib/v1/channel.grpc.pb.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"

namespace httplib {
class Server;
}

namespace behaviorlib::console {

struct GatewayOptions {
  /// Static files of the console's page.
  std::string web_dir;
  /// Messages the event feed keeps for browsers that reconnect.
  size_t replay_capacity = 2000;
  /// Browsers following the event feed at once; more are 503.
  int max_event_clients = 32;
  /// Largest request body (a mission text is the largest).
  size_t max_body_bytes = 256 * 1024;
  /// Deadline of a unary coordinator call.
  std::chrono::milliseconds call_timeout{10000};
  /// How often the mission list is read to find missions to watch.
  std::chrono::milliseconds mission_poll{1000};
  /// Missions watched at once (the running and paused ones).
  size_t max_watched_missions = 16;
  /// The data channel, for the vehicles' state (none: no `vehicle` events).
  std::shared_ptr<grpc::Channel> data_channel;
  /// The topics followed for each robot of the fleet, under robots/{id}/.
  std::vector<std::string> vehicle_topics = {"self_localization/pose", "ground_truth/pose",
                                             "flight_state", "map/occupied"};
  /// At most one `vehicle` event per robot and topic this often; the
  /// subscriptions ask the broker for that rate (max_rate_hz).
  std::chrono::milliseconds vehicle_period{100};
  /// Robots whose vehicle state is followed.
  size_t max_robots = 16;
  /// The map's world as JSON (GET /api/world); empty: a world without boxes.
  std::string world_json;
  /// Where the flight recordings are (clients/recorder); empty: none.
  std::string recordings_dir;
  /// Largest recording opened, and most messages sent of one.
  uint64_t max_recording_bytes = uint64_t{512} << 20;
  size_t max_recording_messages = 200000;
  /// A recording's vehicle samples, at most one per topic this often.
  std::chrono::milliseconds recording_sample_period{100};
  /// HTTPS with these PEM files (both, or neither: HTTP).
  std::string tls_cert_file;
  std::string tls_key_file;
};

class Gateway : private follower::FleetSink {
 public:
  Gateway(std::shared_ptr<grpc::Channel> coordinator, GatewayOptions options);
  /// Stops everything (shutdown()).
  ~Gateway() override;
  Gateway(const Gateway&) = delete;
  Gateway& operator=(const Gateway&) = delete;

  /// Binds host:port (port 0: any free one) and serves on a thread of its
  /// own; follows the coordinator's events and missions.
  absl::Status start(const std::string& host, int port);
  int port() const { return port_; }
  /// Ends the event feeds and the coordinator streams, stops serving.
  void shutdown();

  EventHub& hub() { return hub_; }

 private:
  void onEvent(const v1::FleetEvent& event) override;
  void onMission(const v1::MissionStatus& status) override;
  void onBelief(const v1::Belief& belief) override;
  void onSample(const v1::SubscribeResponse& sample) override;
  void onCoordinator(bool up, const std::string& why) override;
  void routes();
  void recordingRoutes();

  const std::shared_ptr<grpc::Channel> channel_;
  const std::unique_ptr<v1::Coordinator::Stub> stub_;
  const GatewayOptions options_;
  EventHub hub_;
  follower::FleetFollower follower_;
  std::unique_ptr<httplib::Server> server_;
  server_kit::ConfinedDirectory recordings_;
  int port_ = 0;
  std::atomic<int> event_clients_{0};
  std::atomic<bool> http_ended_{false};
  std::atomic<bool> stopped_{false};
  std::thread http_thread_;
};

}  // namespace behaviorlib::console
