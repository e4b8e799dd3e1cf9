#include "behaviorlib/server_kit/transport_security.h"

#include <cstdio>
#include <optional>

#include "absl/flags/flag.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/server_kit/confined_files.h"

ABSL_FLAG(std::string, tls_cert, "",
          "PEM certificate of this process; with --tls-key and --tls-ca, every gRPC server and "
          "client of the process uses mutual TLS (scripts/make-dev-certs.sh makes a set)");
ABSL_FLAG(std::string, tls_key, "", "PEM private key of --tls-cert");
ABSL_FLAG(std::string, tls_ca, "",
          "PEM CA certificates that every peer's certificate must chain to");
ABSL_FLAG(bool, insecure, false,
          "allow plaintext gRPC on an address other than loopback: anyone who can reach the "
          "port can then command, land or kill the vehicles");

namespace behaviorlib::server_kit {
namespace {

constexpr size_t kMaxPemBytes = 1 << 20;

struct ProcessState {
  absl::Mutex mutex;
  std::optional<TransportSecurity> security ABSL_GUARDED_BY(mutex);
  // Loaded once: every channel of the process shares these credentials.
  std::optional<absl::StatusOr<std::shared_ptr<grpc::ChannelCredentials>>> channel
      ABSL_GUARDED_BY(mutex);
};

ProcessState& state() {
  static ProcessState* s = new ProcessState();
  return *s;
}

absl::StatusOr<std::string> readPem(const std::string& flag, const std::string& path) {
  if (path.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat("TLS needs --tls-cert, --tls-key and --tls-ca; ", flag, " is missing"));
  }
  absl::StatusOr<std::string> text = readFileCapped(path, kMaxPemBytes);
  if (!text.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(flag, " ", path, ": ", text.status().message()));
  }
  if (!absl::StrContains(*text, "-----BEGIN ")) {
    return absl::InvalidArgumentError(absl::StrCat(flag, " ", path, ": not a PEM file"));
  }
  return text;
}

// The host part of "host:port", "[v6]:port", "dns:///host:port", "ipv4:host:port".
std::string hostOf(std::string address) {
  for (const char* scheme : {"dns:///", "dns:", "ipv4:", "ipv6:"}) {
    if (absl::StartsWith(address, scheme)) address = address.substr(std::string(scheme).size());
  }
  if (!address.empty() && address.front() == '[') {
    const size_t close = address.find(']');
    return close == std::string::npos ? address : address.substr(1, close - 1);
  }
  const size_t colon = address.rfind(':');
  return colon == std::string::npos ? address : address.substr(0, colon);
}

}  // namespace

absl::StatusOr<TlsMaterial> loadTlsMaterial(const TransportSecurity& security) {
  TlsMaterial material;
  absl::StatusOr<std::string> cert = readPem("--tls-cert", security.cert_file);
  if (!cert.ok()) return cert.status();
  absl::StatusOr<std::string> key = readPem("--tls-key", security.key_file);
  if (!key.ok()) return key.status();
  absl::StatusOr<std::string> ca = readPem("--tls-ca", security.ca_file);
  if (!ca.ok()) return ca.status();
  material.cert_pem = std::move(*cert);
  material.key_pem = std::move(*key);
  material.ca_pem = std::move(*ca);
  return material;
}

TransportSecurity transportSecurityFromFlags() {
  TransportSecurity security;
  security.cert_file = absl::GetFlag(FLAGS_tls_cert);
  security.key_file = absl::GetFlag(FLAGS_tls_key);
  security.ca_file = absl::GetFlag(FLAGS_tls_ca);
  security.insecure = absl::GetFlag(FLAGS_insecure);
  return security;
}

const TransportSecurity& processTransport() {
  ProcessState& s = state();
  absl::MutexLock lock(&s.mutex);
  if (!s.security) s.security = transportSecurityFromFlags();
  // Set once and never changed after the first server or channel: the
  // reference stays valid.
  return *s.security;
}

void setProcessTransport(TransportSecurity security) {
  ProcessState& s = state();
  absl::MutexLock lock(&s.mutex);
  s.security = std::move(security);
  s.channel.reset();
}

absl::Status checkProcessTransport() {
  const TransportSecurity& security = processTransport();
  if (!security.tls()) return absl::OkStatus();
  return loadTlsMaterial(security).status();
}

absl::StatusOr<std::shared_ptr<grpc::ServerCredentials>> serverCredentials(
    const TransportSecurity& security) {
  if (!security.tls()) return grpc::InsecureServerCredentials();
  absl::StatusOr<TlsMaterial> material = loadTlsMaterial(security);
  if (!material.ok()) return material.status();
  grpc::SslServerCredentialsOptions options(
      GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY);
  options.pem_root_certs = material->ca_pem;
  options.pem_key_cert_pairs.push_back({material->key_pem, material->cert_pem});
  return grpc::SslServerCredentials(options);
}

absl::StatusOr<std::shared_ptr<grpc::ChannelCredentials>> channelCredentials(
    const TransportSecurity& security) {
  if (!security.tls()) return grpc::InsecureChannelCredentials();
  absl::StatusOr<TlsMaterial> material = loadTlsMaterial(security);
  if (!material.ok()) return material.status();
  grpc::SslCredentialsOptions options;
  options.pem_root_certs = material->ca_pem;
  options.pem_private_key = material->key_pem;
  options.pem_cert_chain = material->cert_pem;
  return grpc::SslCredentials(options);
}

bool isLoopbackAddress(const std::string& address) {
  if (absl::StartsWith(address, "unix:") || absl::StartsWith(address, "unix-abstract:")) {
    return true;
  }
  const std::string host = hostOf(address);
  return host == "localhost" || host == "::1" || absl::StartsWith(host, "127.");
}

absl::Status checkListenAddress(const std::string& address, const TransportSecurity& security,
                                const std::string& flag) {
  if (security.tls() || isLoopbackAddress(address)) return absl::OkStatus();
  if (security.insecure) {
    std::fprintf(stderr,
                 "warning: %s %s without TLS (--insecure): anyone who can reach this port can "
                 "command, land or kill the vehicles\n",
                 flag.c_str(), address.c_str());
    return absl::OkStatus();
  }
  return absl::InvalidArgumentError(absl::StrCat(
      flag, " ", address,
      " is not a loopback address and there is no TLS: anyone who could reach it could "
      "command, land or kill the vehicles. Give --tls-cert, --tls-key and --tls-ca "
      "(scripts/make-dev-certs.sh), or --insecure to accept that risk on a private network"));
}

std::shared_ptr<grpc::Channel> makeChannel(const std::string& target,
                                           const grpc::ChannelArguments& args) {
  const TransportSecurity& security = processTransport();
  std::shared_ptr<grpc::ChannelCredentials> credentials;
  {
    ProcessState& s = state();
    absl::MutexLock lock(&s.mutex);
    if (!s.channel) {
      s.channel = channelCredentials(security);
      if (!s.channel->ok()) {
        std::fprintf(stderr, "error: no gRPC channel can be made: %s\n",
                     std::string(s.channel->status().message()).c_str());
      }
    }
    if (s.channel->ok()) credentials = **s.channel;
  }
  if (!credentials) {
    // Never plaintext in place of TLS: a channel to nowhere, whose calls
    // fail UNAVAILABLE.
    return grpc::CreateCustomChannel("unix:/nonexistent/behaviorlib-tls-files-unreadable",
                                     grpc::InsecureChannelCredentials(), args);
  }
  return grpc::CreateCustomChannel(target, credentials, args);
}

}  // namespace behaviorlib::server_kit
