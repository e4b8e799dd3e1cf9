#pragma once

// The broker's link to a fleet's other hosts over NATS (decision 39). Each
// host runs its own broker (same-host subscribers keep their shared-memory
// rings); the brokers of a fleet share the topics that cross hosts through
// NATS: each broker a client of the ground's server (or its cluster), with
// mutual TLS and a NATS user per host that bounds what it may publish.
//
//   NatsLinkOptions options;
//   options.url = "nats://127.0.0.1:4222";
//   options.name = "drone1";
//   absl::StatusOr<std::unique_ptr<NatsLink>> link = NatsLink::start(broker, options, registry);
//
// What travels (subjects are the topic's segments, '.' written as '~'):
//   bl.t.<topic>     a sample: its google.protobuf.Any, serialized
//   bl.want.<name>   the topics broker <name> wants (WatchInterestResponse),
//                    on every change and once a second
//   bl.hello         a broker that (re)connected asks the others to announce
// A broker sends a topic's samples only while another broker wants it, and
// subscribes on NATS only to the topics its own host wants, so an idle link
// carries the announcements and nothing else.

#include <chrono>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "behaviorlib/channel/broker.h"

namespace prometheus {
class Registry;
}  // namespace prometheus

namespace behaviorlib::channel {

struct NatsLinkOptions {
  /// The NATS server(s): "nats://host:4222", or "tls://..."; several,
  /// comma-separated, are tried in turn.
  std::string url;
  /// This broker's name in the fleet (letters, digits, '_' and '-'): its
  /// announcements' subject, and its client name on the server.
  std::string name;
  /// Topic prefixes that never cross hosts, in either direction (a vehicle
  /// takes "clock" from its own autopilot).
  std::vector<std::string> local_prefixes;
  /// Mutual TLS to the server: this broker's certificate chain and key, and
  /// the CA that signed the server's. All three or none.
  std::string tls_cert;
  std::string tls_key;
  std::string tls_ca;
  /// How often the wanted set is announced while it does not change, and
  /// how long another broker's announcement counts without a new one.
  std::chrono::milliseconds announce_period{1000};
  std::chrono::milliseconds want_ttl{3500};
  /// Link loss detection: the client pings the server this often and
  /// counts the link lost after this many unanswered pings.
  std::chrono::milliseconds ping_interval{1000};
  int max_pings_out = 2;
  /// At most this many frames a second go out (0: every sample at once):
  /// a radio link's budget. A frame is the newest sample of every topic
  /// that has one since the last, written together; a sample waits at most
  /// one interval for its frame (the ones it replaced are counted, never
  /// sent). Each topic thus crosses at most this many times a second.
  double max_rate_hz = 0;
  /// Samples kept while the link is down, sent when it returns; beyond,
  /// samples are dropped and counted.
  int reconnect_buffer_bytes = 64 * 1024;
  /// Bounds on what other brokers announce.
  std::size_t max_peers = 1024;
  std::size_t max_wanted_per_peer = 10'000;
};

/// The NATS subject of a topic, and back (nullopt: not a topic subject).
std::string topicSubject(absl::string_view topic);
std::optional<std::string> subjectTopic(absl::string_view subject);

class NatsLink final : public BrokerLink {
 public:
  /// Connects (or keeps trying to, in the background, while the server is
  /// not up yet) and attaches to `broker`. INVALID_ARGUMENT for bad
  /// options. Metrics (behaviorlib_channel_link_*) go on `registry`; the
  /// broker and the registry must outlive the link.
  static absl::StatusOr<std::unique_ptr<NatsLink>> start(Broker& broker, NatsLinkOptions options,
                                                         prometheus::Registry& registry);
  /// Detaches from the broker and closes the connection.
  ~NatsLink() override;
  NatsLink(const NatsLink&) = delete;
  NatsLink& operator=(const NatsLink&) = delete;

  void localInterestChanged(std::vector<std::string> wanted) override;
  void localSample(const std::string& topic, const v1::SubscribeResponse& sample) override;

  class Impl;

 private:
  explicit NatsLink(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
  Broker* broker_ = nullptr;
};

}  // namespace behaviorlib::channel
