// channel_broker: serves behaviorlib.v1.DataChannel (the common data channel).
//
//   channel_broker --listen 127.0.0.1:50051 --metrics-listen 127.0.0.1:9100
//
// Exits 0 after SIGTERM/SIGINT (every stream ended), 1 when it cannot bind
// or on a bad flag.

#include <grpcpp/grpcpp.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <memory>
#include <string>

#include "absl/flags/flag.h"
#include "absl/strings/str_split.h"
#include "behaviorlib/channel/broker.h"
#include "behaviorlib/channel/nats_link.h"
#include "behaviorlib/server_kit/flags.h"
#include "behaviorlib/server_kit/server_runtime.h"

ABSL_FLAG(std::string, listen, "127.0.0.1:50051", "gRPC address host:port (port 0: any free port)");
ABSL_FLAG(std::string, metrics_listen, "127.0.0.1:9100",
          "Prometheus /metrics address host:port (port 0: any free port; empty: disabled)");
ABSL_FLAG(std::string, port_file, "",
          "write the bound ports here as grpc_port=N / metrics_port=M once serving");
ABSL_FLAG(bool, shared_memory, behaviorlib::channel::BrokerOptions().shared_memory,
          "deliver to subscribers on this host that ask for it through shared-memory rings "
          "under /dev/shm (false: every sample on its gRPC stream)");

ABSL_FLAG(std::string, link_url, "",
          "NATS server(s) of the fleet's data engine, e.g. nats://127.0.0.1:4222 (comma-separated "
          "for several): topics wanted on other hosts travel there (decision 39); empty: this host "
          "only");
ABSL_FLAG(std::string, link_name, "",
          "this broker's name in the fleet (letters, digits, '_', '-'; default: the host name)");
ABSL_FLAG(std::string, link_local, "",
          "comma-separated topic prefixes that never cross hosts (e.g. clock on a vehicle that "
          "takes the time from its own autopilot)");
ABSL_FLAG(double, link_max_rate_hz, 0.0,
          "at most this many frames a second go to other hosts (0: every sample at once): a "
          "radio link's budget; a frame is the newest sample of each topic since the last, "
          "written together");
ABSL_FLAG(double, link_announce_period_s, 1.0,
          "how often the link repeats this host's wants to the other hosts (they are also "
          "announced at once on every change)");
ABSL_FLAG(double, link_want_ttl_s, 3.5,
          "how long another host's announced wants count without a new announcement (longer "
          "than the period; the same on every host of a fleet)");
ABSL_FLAG(std::string, link_tls_cert, "", "the link's client certificate chain (mutual TLS)");
ABSL_FLAG(std::string, link_tls_key, "", "the link's private key");
ABSL_FLAG(std::string, link_tls_ca, "", "the CA that signed the NATS server's certificate");

ABSL_FLAG(int, max_topics, static_cast<int>(behaviorlib::channel::BrokerOptions().max_topics),
          "topics the broker keeps; a new topic beyond is RESOURCE_EXHAUSTED (1..1000000)");

int main(int argc, char** argv) {
  using behaviorlib::server_kit::fatal;
  using behaviorlib::server_kit::ServerRuntime;
  // Before any thread exists, so that every thread inherits the mask and the
  // signal is only taken by waitForShutdownSignal().
  ServerRuntime::blockShutdownSignals();
  const std::string program = "channel_broker";

  behaviorlib::server_kit::parseFlags(
      argc, argv,
      "the common data channel broker (behaviorlib.v1.DataChannel): typed samples on named "
      "topics");
  const std::string listen = absl::GetFlag(FLAGS_listen);
  const std::string metrics_listen = absl::GetFlag(FLAGS_metrics_listen);
  const std::string port_file = absl::GetFlag(FLAGS_port_file);
  behaviorlib::channel::BrokerOptions options;
  options.shared_memory = absl::GetFlag(FLAGS_shared_memory);
  if (const int topics = absl::GetFlag(FLAGS_max_topics); topics < 1 || topics > 1000000) {
    return fatal(program,
                 absl::InvalidArgumentError("--max-topics must be within [1, 1000000], got " +
                                            std::to_string(topics)));
  } else {
    options.max_topics = static_cast<std::size_t>(topics);
  }

  ServerRuntime runtime;
  std::string error;
  if (!runtime.startMetrics(metrics_listen, &error)) return fatal(program, error);

  // Declared after `runtime` but shut down explicitly below on every path
  // where the server was started, so the server never outlives the broker.
  behaviorlib::channel::Broker broker(runtime.registry(), options);
  std::unique_ptr<behaviorlib::channel::NatsLink> link;
  if (const std::string url = absl::GetFlag(FLAGS_link_url); !url.empty()) {
    behaviorlib::channel::NatsLinkOptions link_options;
    link_options.url = url;
    link_options.name = absl::GetFlag(FLAGS_link_name);
    if (link_options.name.empty()) {
      char host[256] = {};
      if (gethostname(host, sizeof(host) - 1) == 0) link_options.name = host;
    }
    link_options.local_prefixes =
        absl::StrSplit(absl::GetFlag(FLAGS_link_local), ',', absl::SkipEmpty());
    link_options.max_rate_hz = absl::GetFlag(FLAGS_link_max_rate_hz);
    const auto millis = [](double s) {
      return std::chrono::milliseconds(static_cast<int64_t>(std::clamp(s, 0.0, 3600.0) * 1e3));
    };
    link_options.announce_period = millis(absl::GetFlag(FLAGS_link_announce_period_s));
    link_options.want_ttl = millis(absl::GetFlag(FLAGS_link_want_ttl_s));
    link_options.tls_cert = absl::GetFlag(FLAGS_link_tls_cert);
    link_options.tls_key = absl::GetFlag(FLAGS_link_tls_key);
    link_options.tls_ca = absl::GetFlag(FLAGS_link_tls_ca);
    auto started =
        behaviorlib::channel::NatsLink::start(broker, std::move(link_options), runtime.registry());
    if (!started.ok()) return fatal(program, started.status());
    link = std::move(*started);
  }
  grpc::ServerBuilder builder;
  builder.RegisterService(&broker);
  if (!runtime.startServer(builder, listen, {"behaviorlib.v1.DataChannel"}, &error)) {
    return fatal(program, error);
  }
  if (!runtime.writePortFile(port_file, &error)) {
    runtime.shutdown(std::chrono::milliseconds(0));
    return fatal(program, error);
  }
  std::fprintf(stderr, "%s: serving behaviorlib.v1.DataChannel on port %d (metrics port %d)\n",
               program.c_str(), runtime.grpcPort(), runtime.metricsPort());

  const int sig = ServerRuntime::waitForShutdownSignal();
  std::fprintf(stderr, "%s: signal %d, shutting down\n", program.c_str(), sig);
  // The link goes first: nothing more arrives from other hosts.
  link.reset();
  // End every stream first: Server::Shutdown would otherwise wait for
  // subscribers that never hang up.
  broker.shutdown();
  // Every call is finished by now, except quick unary ones; what remains is
  // gRPC's graceful GOAWAY exchange with idle client connections, which can
  // wait for clients that do not poll. Bound it tightly.
  runtime.shutdown(std::chrono::milliseconds(500));
  return 0;
}
