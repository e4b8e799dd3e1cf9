// console: the operator's console in the browser, and its gateway to the
// coordinator (decision 35).
//
//   console --listen 127.0.0.1:8090 --coordinator 127.0.0.1:50060
//
// Serves the console's page and an HTTP API (gateway.h) that calls the
// coordinator over gRPC, with the process's transport security (mTLS with
// --tls-cert/--tls-key/--tls-ca, which also make the page HTTPS). Exits 0
// after SIGTERM/SIGINT, 1 when it cannot bind, 2 on a bad flag.

#include <httplib.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include "absl/flags/flag.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "behaviorlib/console/gateway.h"
#include "behaviorlib/server_kit/flags.h"
#include "behaviorlib/server_kit/server_runtime.h"
#include "behaviorlib/server_kit/transport_security.h"
#include "world_json.h"

ABSL_FLAG(std::string, listen, "127.0.0.1:8090",
          "HTTP address host:port of the console (port 0: any free port)");
ABSL_FLAG(std::string, coordinator, "127.0.0.1:50060", "the coordinator's gRPC address");
ABSL_FLAG(std::string, channel, "",
          "the data channel's gRPC address, for the vehicles' pose and flight status (empty: "
          "none)");
ABSL_FLAG(std::string, web_dir, BEHAVIORLIB_CONSOLE_WEB_DIR, "the console's page and scripts");
ABSL_FLAG(std::string, world, "",
          "a simulator world file (YAML) drawn under the vehicles on the console's map");
ABSL_FLAG(std::string, recordings_dir, "",
          "the flight recordings (*.mcap) the console's page may open and scrub through");
ABSL_FLAG(std::string, port_file, "", "write the bound port here as http_port=N once serving");
ABSL_FLAG(std::string, probe, "",
          "health check: GET /healthz of the console at this host:port (HTTPS when the TLS "
          "flags are given, verified against --tls-ca), exit 0 when it answers 200");
ABSL_FLAG(int, max_event_clients, behaviorlib::console::GatewayOptions().max_event_clients,
          "browsers following the live event feed at once (1..1000)");

namespace {

// host:port -> (host, port); false when it is not one.
bool splitAddress(const std::string& address, std::string* host, int* port) {
  const size_t colon = address.rfind(':');
  if (colon == std::string::npos || colon == 0) return false;
  *host = address.substr(0, colon);
  if (host->size() > 2 && host->front() == '[' && host->back() == ']') {
    *host = host->substr(1, host->size() - 2);
  }
  return absl::SimpleAtoi(address.substr(colon + 1), port) && *port >= 0 && *port <= 65535;
}

// The --probe health check (a container has no curl).
int probe(const std::string& address, const behaviorlib::server_kit::TransportSecurity& security) {
  std::string host;
  int port = 0;
  if (!splitAddress(address, &host, &port) || port == 0) {
    std::fprintf(stderr, "console: --probe must be host:port, got '%s'\n", address.c_str());
    return 2;
  }
  auto check = [&](auto& client) {
    client.set_connection_timeout(std::chrono::seconds(2));
    client.set_read_timeout(std::chrono::seconds(2));
    const httplib::Result result = client.Get("/healthz");
    if (result && result->status == 200) return 0;
    std::fprintf(stderr, "console: %s is not healthy (%s)\n", address.c_str(),
                 result ? std::to_string(result->status).c_str()
                        : httplib::to_string(result.error()).c_str());
    return 1;
  };
  if (security.tls()) {
    httplib::SSLClient client(host, port);
    client.set_ca_cert_path(security.ca_file.c_str());
    client.enable_server_certificate_verification(true);
    return check(client);
  }
  httplib::Client client(host, port);
  return check(client);
}

bool writePortFile(const std::string& path, int port) {
  if (path.empty()) return true;
  const std::string temporary = path + ".tmp";
  {
    std::ofstream out(temporary, std::ios::trunc);
    out << "http_port=" << port << "\n";
    if (!out.good()) return false;
  }
  std::error_code error;
  std::filesystem::rename(temporary, path, error);
  return !error;
}

}  // namespace

int main(int argc, char** argv) {
  using behaviorlib::server_kit::fatal;
  using behaviorlib::server_kit::ServerRuntime;
  ServerRuntime::blockShutdownSignals();
  const std::string program = "console";
  behaviorlib::server_kit::parseFlags(
      argc, argv, "the operator's console in the browser, and its gateway to the coordinator");

  if (absl::Status s = behaviorlib::server_kit::checkProcessTransport(); !s.ok()) {
    return fatal(program, s);
  }
  const auto& security = behaviorlib::server_kit::processTransport();
  if (const std::string target = absl::GetFlag(FLAGS_probe); !target.empty()) {
    return probe(target, security);
  }

  std::string host;
  int port = 0;
  const std::string listen = absl::GetFlag(FLAGS_listen);
  if (!splitAddress(listen, &host, &port)) {
    return fatal(program,
                 absl::InvalidArgumentError("--listen must be host:port, got '" + listen + "'"));
  }
  const int clients = absl::GetFlag(FLAGS_max_event_clients);
  if (clients < 1 || clients > 1000) {
    return fatal(program, absl::InvalidArgumentError(absl::StrCat(
                              "--max-event-clients must be within [1, 1000], got ", clients)));
  }
  if (absl::Status s = behaviorlib::server_kit::checkListenAddress(listen, security); !s.ok()) {
    return fatal(program, s);
  }

  behaviorlib::console::GatewayOptions options;
  options.web_dir = absl::GetFlag(FLAGS_web_dir);
  options.max_event_clients = clients;
  options.tls_cert_file = security.cert_file;
  options.tls_key_file = security.key_file;
  options.recordings_dir = absl::GetFlag(FLAGS_recordings_dir);
  if (const std::string world = absl::GetFlag(FLAGS_world); !world.empty()) {
    absl::StatusOr<std::string> json = behaviorlib::console::worldJson(world);
    if (!json.ok()) {
      return fatal(program, absl::InvalidArgumentError("--world: " + json.status().ToString()));
    }
    options.world_json = std::move(*json);
  }
  if (const std::string channel = absl::GetFlag(FLAGS_channel); !channel.empty()) {
    options.data_channel = behaviorlib::server_kit::makeChannel(channel);
  }
  const std::string coordinator = absl::GetFlag(FLAGS_coordinator);
  behaviorlib::console::Gateway gateway(behaviorlib::server_kit::makeChannel(coordinator), options);
  if (absl::Status s = gateway.start(host, port); !s.ok()) return fatal(program, s);
  if (!writePortFile(absl::GetFlag(FLAGS_port_file), gateway.port())) {
    gateway.shutdown();
    return fatal(program, "cannot write --port-file " + absl::GetFlag(FLAGS_port_file));
  }
  std::fprintf(stderr, "%s: serving the console on %s://%s:%d/ (coordinator %s)\n", program.c_str(),
               options.tls_cert_file.empty() ? "http" : "https", host.c_str(), gateway.port(),
               coordinator.c_str());

  const int sig = ServerRuntime::waitForShutdownSignal();
  std::fprintf(stderr, "%s: signal %d, shutting down\n", program.c_str(), sig);
  gateway.shutdown();
  return 0;
}
