#include "simulator/service/channel_routes.h"

#include <set>
#include <utility>

#include "behaviorlib/channel/topic.h"

namespace behaviorlib::sim {

ChannelRoutes::ChannelRoutes(const std::string& main,
                             const std::map<std::string, std::string>& vehicles) {
  routes_.push_back({"", std::make_unique<channel::ChannelClient>(main), nullptr});
  for (const auto& [robot_id, address] : vehicles) {
    routes_.push_back({robot_id, std::make_unique<channel::ChannelClient>(address), nullptr});
  }
}

ChannelRoutes::~ChannelRoutes() { stopWatching(); }

void ChannelRoutes::stopWatching() {
  // The watches call back into their owners: gone before the clients.
  for (Route& route : routes_) route.interest.reset();
}

const ChannelRoutes::Route& ChannelRoutes::routeOf(const std::string& topic) const {
  constexpr std::string_view kRobots = "robots/";
  if (routes_.size() > 1 && topic.compare(0, kRobots.size(), kRobots) == 0) {
    const std::size_t end = topic.find('/', kRobots.size());
    const std::string_view robot =
        std::string_view(topic).substr(kRobots.size(), end - kRobots.size());
    for (std::size_t i = 1; i < routes_.size(); ++i) {
      if (routes_[i].robot_id == robot) return routes_[i];
    }
  }
  return routes_[0];
}

absl::Status ChannelRoutes::publishAll(
    const std::vector<channel::ChannelClient::TopicSample>& samples, bool sync) {
  const auto publish = [sync](channel::ChannelClient& client, const auto& batch) {
    return sync ? client.publishAllAndSync(batch) : client.publishAll(batch);
  };
  if (routes_.size() == 1) return publish(*routes_[0].client, samples);
  std::map<const Route*, std::vector<channel::ChannelClient::TopicSample>> batches;
  if (sync) {
    for (const Route& route : routes_) batches[&route];  // each is synced
  }
  for (const auto& sample : samples) {
    if (sample.topic == channel::kClockTopic) {
      for (const Route& route : routes_) batches[&route].push_back(sample);
    } else {
      batches[&routeOf(sample.topic)].push_back(sample);
    }
  }
  absl::Status first = absl::OkStatus();
  for (const auto& [route, batch] : batches) {
    absl::Status s = publish(*route->client, batch);
    if (first.ok() && !s.ok()) first = std::move(s);
  }
  return first;
}

absl::Status ChannelRoutes::sync() {
  absl::Status first = absl::OkStatus();
  for (Route& route : routes_) {
    absl::Status s = route.client->sync();
    if (first.ok() && !s.ok()) first = std::move(s);
  }
  return first;
}

std::map<std::string, std::map<std::string, uint64_t>> ChannelRoutes::acceptedSeqsByDomain() const {
  std::map<std::string, std::map<std::string, uint64_t>> seqs;
  for (const Route& route : routes_) seqs[route.robot_id] = route.client->acceptedSeqs();
  return seqs;
}

std::string ChannelRoutes::domainOf(const std::string& robot_id) const {
  for (std::size_t i = 1; i < routes_.size(); ++i) {
    if (routes_[i].robot_id == robot_id) return robot_id;
  }
  return "";
}

std::vector<v1::TopicInfo> ChannelRoutes::listTopics(const std::string& prefix,
                                                     std::chrono::milliseconds timeout) const {
  std::vector<v1::TopicInfo> all;
  for (const Route& route : routes_) {
    auto topics = route.client->listTopics(prefix, timeout);
    if (topics.ok()) all.insert(all.end(), topics->begin(), topics->end());
  }
  return all;
}

void ChannelRoutes::gatePublishing(const std::string& prefix) {
  for (Route& route : routes_) route.client->gatePublishing(prefix);
}

void ChannelRoutes::watchInterest(const std::string& prefix, std::function<void()> on_change) {
  for (Route& route : routes_) route.interest = route.client->watchInterest(prefix, on_change);
}

bool ChannelRoutes::wanted(const std::string& topic) const {
  const Route& route = routeOf(topic);
  return route.interest == nullptr || route.interest->wanted(topic);
}

double ChannelRoutes::maxRateHz(const std::string& topic) const {
  const Route& route = routeOf(topic);
  return route.interest == nullptr ? 0 : route.interest->maxRateHz(topic);
}

bool ChannelRoutes::known() const {
  for (const Route& route : routes_) {
    if (route.interest == nullptr || !route.interest->known()) return false;
  }
  return true;
}

std::vector<std::string> ChannelRoutes::wantedTopics() const {
  std::set<std::string> all;
  for (const Route& route : routes_) {
    if (route.interest == nullptr) continue;
    for (auto& topic : route.interest->wantedTopics()) all.insert(std::move(topic));
  }
  return {all.begin(), all.end()};
}

}  // namespace behaviorlib::sim
