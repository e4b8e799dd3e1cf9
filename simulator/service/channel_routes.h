#pragma once

// ChannelRoutes: where the simulator's samples go. Usually one broker (the
// data channel of `--channel`). In a fleet across hosts, the simulator stands
// in for every vehicle's autopilot, and an autopilot publishes to its own
// vehicle's broker: `--vehicle-channel drone1=HOST:PORT` sends the topics of
// robots/drone1/ there, over what stands for the vehicle's onboard link, and
// the clock to every broker (decision 39). Everything else goes to the main
// broker.
//
//   ChannelRoutes routes("10.0.0.2:50051", {{"drone1", "10.1.0.11:50051"}});
//   routes.publishAll(samples);           // grouped per broker
//   routes.watchInterest("robots/", cb);  // the union of every broker's wants

#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "behaviorlib/channel/channel_client.h"

namespace behaviorlib::sim {

class ChannelRoutes {
 public:
  /// `main` takes the clock and every topic without a vehicle route;
  /// `vehicles` maps robot ids to their own brokers.
  ChannelRoutes(const std::string& main, const std::map<std::string, std::string>& vehicles = {});
  ~ChannelRoutes();
  ChannelRoutes(const ChannelRoutes&) = delete;
  ChannelRoutes& operator=(const ChannelRoutes&) = delete;

  /// Publishes each sample to its broker (the clock to all), one batch per
  /// broker; the first error. With `sync`, also sync() in the same round
  /// trip (ChannelClient::publishAllAndSync; a broker with no sample here is
  /// synced alone).
  absl::Status publishAll(const std::vector<channel::ChannelClient::TopicSample>& samples,
                          bool sync = false);
  /// ChannelClient::sync on every broker; the first error.
  absl::Status sync();
  /// The topic_seq each broker accepted last, per topic, per broker: the
  /// robot id of a vehicle's broker, "" for the main one (the deterministic
  /// mode's domains, TimeGrants::setDomainOf; each broker numbers a topic,
  /// the clock too, its own way).
  std::map<std::string, std::map<std::string, uint64_t>> acceptedSeqsByDomain() const;
  /// The domain of a robot's followers: its own broker's, or the main one.
  std::string domainOf(const std::string& robot_id) const;
  /// The topics under `prefix` of every broker.
  std::vector<v1::TopicInfo> listTopics(const std::string& prefix,
                                        std::chrono::milliseconds timeout) const;
  void gatePublishing(const std::string& prefix);

  /// Watches every broker's wanted set under `prefix`; `on_change` runs
  /// when any changes.
  void watchInterest(const std::string& prefix, std::function<void()> on_change);
  /// Ends the watches: `on_change` runs no more.
  void stopWatching();
  /// Whether `topic` is wanted at the broker it goes to; true while that
  /// broker's watch is not known (as an InterestWatch).
  bool wanted(const std::string& topic) const;
  /// The rate `topic` is wanted at by its broker's readers, in samples a
  /// second of wall time (InterestWatch::maxRateHz); 0: every sample.
  double maxRateHz(const std::string& topic) const;
  /// Every watch has its broker's set.
  bool known() const;
  /// The union of the wanted sets.
  std::vector<std::string> wantedTopics() const;

 private:
  struct Route {
    std::string robot_id;  // empty: the main broker
    std::unique_ptr<channel::ChannelClient> client;
    std::unique_ptr<channel::InterestWatch> interest;
  };
  // The route of a topic (the main one unless robots/<id>/ has its own).
  const Route& routeOf(const std::string& topic) const;

  std::vector<Route> routes_;  // [0]: the main broker
};

}  // namespace behaviorlib::sim
