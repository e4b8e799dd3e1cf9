// tls_bench: what mutual TLS, the access policy and the gRPC server metrics
// cost per call. One coordinator per configuration, on loopback, each
// answering the same unary call (ListMissions, an empty list) from one client
// on one channel:
//   plaintext, no metrics  --grpc-metrics=false, no TLS (the floor)
//   plaintext              --listen on loopback, no TLS, gRPC metrics (the default)
//   mtls                   --tls-cert/--tls-key/--tls-ca
//   mtls+policy            the same with --access-policy (the authorizer on every call)
// Rounds alternate the configurations so that the machine's load falls on
// each alike. Prints a markdown table: median and p99 per configuration and
// their excess over the floor.
//
//   tls_bench                  # 5 rounds of 2000 calls per configuration
//   tls_bench --smoke          # 1 round of 50: fails on errors, not timings

#include <grpcpp/grpcpp.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "support/server_process.h"

namespace {

namespace v1 = behaviorlib::v1;

std::string read(const std::string& path) {
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

double percentile(std::vector<double> values, double p) {
  std::sort(values.begin(), values.end());
  const size_t i = std::min(values.size() - 1, static_cast<size_t>(p * values.size()));
  return values[i];
}

struct Configuration {
  std::string name;
  std::vector<std::string> flags;
  bool tls = false;
  std::unique_ptr<support::ServerProcess> server;
  std::unique_ptr<v1::Coordinator::Stub> stub;
  std::vector<double> micros;
};

}  // namespace

int main(int argc, char** argv) {
  const bool smoke = argc > 1 && std::strcmp(argv[1], "--smoke") == 0;
  const int rounds = smoke ? 1 : 5;
  const int calls = smoke ? 50 : 2000;

  char dir_template[] = "/tmp/tls_bench_XXXXXX";
  if (mkdtemp(dir_template) == nullptr) return 1;
  const std::string dir = dir_template;
  const std::string certs = dir + "/certs";
  const std::string make = std::string(BEHAVIORLIB_MAKE_DEV_CERTS) + " --out " + certs +
                           " coordinator operator > /dev/null";
  if (std::system(make.c_str()) != 0) {
    std::fprintf(stderr, "tls_bench: cannot make certificates\n");
    return 1;
  }
  std::ofstream(dir + "/policy.yaml") << "identities:\n"
                                         "  - certificate: behaviorlib:operator\n"
                                         "    roles: [viewer, operator]\n";
  const std::vector<std::string> tls = {"--tls-cert", certs + "/coordinator.pem",
                                        "--tls-key",  certs + "/coordinator.key",
                                        "--tls-ca",   certs + "/ca.pem"};
  std::vector<Configuration> configurations(4);
  configurations[0].name = "plaintext, no gRPC metrics (floor)";
  configurations[0].flags = {"--grpc-metrics=false"};
  configurations[1].name = "plaintext";
  configurations[2].name = "mtls";
  configurations[2].flags = tls;
  configurations[2].tls = true;
  configurations[3].name = "mtls + access policy";
  configurations[3].flags = tls;
  configurations[3].flags.insert(configurations[3].flags.end(),
                                 {"--access-policy", dir + "/policy.yaml"});
  configurations[3].tls = true;

  grpc::SslCredentialsOptions client;
  client.pem_root_certs = read(certs + "/ca.pem");
  client.pem_private_key = read(certs + "/operator.key");
  client.pem_cert_chain = read(certs + "/operator.pem");
  int status = 0;
  for (auto& c : configurations) {
    std::vector<std::string> args = {"--metrics-listen", ""};
    args.insert(args.end(), c.flags.begin(), c.flags.end());
    c.server = std::make_unique<support::ServerProcess>(BEHAVIORLIB_COORDINATOR_PATH, args);
    if (!c.server->start()) {
      std::fprintf(stderr, "tls_bench: %s: %s\n", c.name.c_str(), c.server->error().c_str());
      return 1;
    }
    c.stub = v1::Coordinator::NewStub(
        grpc::CreateChannel(c.server->address(), c.tls ? grpc::SslCredentials(client)
                                                       : grpc::InsecureChannelCredentials()));
  }
  for (int round = 0; round <= rounds && status == 0; ++round) {
    for (auto& c : configurations) {
      for (int i = 0; i < calls; ++i) {
        grpc::ClientContext context;
        context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
        v1::ListMissionsResponse response;
        const auto t0 = std::chrono::steady_clock::now();
        const grpc::Status s = c.stub->ListMissions(&context, v1::ListMissionsRequest(), &response);
        const auto t1 = std::chrono::steady_clock::now();
        if (!s.ok()) {
          std::fprintf(stderr, "tls_bench: %s: %s\n", c.name.c_str(), s.error_message().c_str());
          status = 1;
          break;
        }
        // Round 0 warms the connections up (handshakes) and is not counted.
        if (round > 0)
          c.micros.push_back(std::chrono::duration<double, std::micro>(t1 - t0).count());
      }
    }
  }
  if (status == 0) {
    const double floor_median = percentile(configurations[0].micros, 0.5);
    std::printf("| configuration | calls | median µs | p99 µs | median over the floor µs |\n");
    std::printf("|---|---|---|---|---|\n");
    for (const auto& c : configurations) {
      const double median = percentile(c.micros, 0.5);
      std::printf("| %s | %zu | %.1f | %.1f | %+.1f |\n", c.name.c_str(), c.micros.size(), median,
                  percentile(c.micros, 0.99), median - floor_median);
    }
  }
  for (auto& c : configurations) c.server->terminate();
  std::filesystem::remove_all(dir);
  return status;
}
