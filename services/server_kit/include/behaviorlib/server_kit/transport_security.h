#pragma once

// Transport security of every gRPC server and client of behaviorlib: mutual
// TLS from three PEM files given as flags, or plaintext on loopback.
//
//   --tls-cert FILE   this process's certificate (chain), PEM
//   --tls-key FILE    its private key, PEM
//   --tls-ca FILE     the CA certificates a peer's certificate must chain to
//   --insecure        plaintext on an address other than loopback
//
// With TLS, a server requires and verifies a client certificate from the CA,
// and a client verifies the server's certificate against the CA and the
// host it dials (a SAN of the certificate: scripts/make-dev-certs.sh gives
// each process its service name, localhost and 127.0.0.1). Without TLS, a
// server may bind only a loopback address unless --insecure says that the
// risk is accepted: anyone who reaches the port can then fly, land or kill
// the vehicles.
//
//   ServerRuntime::startServer uses serverCredentials(processTransport());
//   clients dial with makeChannel(address).
//
// processTransport() is read from the flags once, after parseFlags; a test
// or an embedding program sets it with setProcessTransport() first.

#include <grpcpp/grpcpp.h>

#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace behaviorlib::server_kit {

struct TransportSecurity {
  std::string cert_file;  ///< PEM certificate (chain) of this process
  std::string key_file;   ///< PEM private key of cert_file
  std::string ca_file;    ///< PEM CA certificates that peers must chain to
  /// Plaintext on a non-loopback address is allowed (the operator accepts
  /// that anyone who reaches it may command the fleet).
  bool insecure = false;

  bool tls() const { return !cert_file.empty() || !key_file.empty() || !ca_file.empty(); }
};

/// The PEM texts of a TransportSecurity, read and checked.
struct TlsMaterial {
  std::string cert_pem;
  std::string key_pem;
  std::string ca_pem;
};

/// INVALID_ARGUMENT naming the flag: TLS needs all three files, each a
/// readable PEM file (of at most 1 MiB).
absl::StatusOr<TlsMaterial> loadTlsMaterial(const TransportSecurity& security);

/// From --tls-cert, --tls-key, --tls-ca and --insecure.
TransportSecurity transportSecurityFromFlags();

/// The process's transport setting (from the flags unless set before).
const TransportSecurity& processTransport();
/// Sets the process's transport setting; call before any server or channel
/// is made (tests, programs that embed a server).
void setProcessTransport(TransportSecurity security);

/// Checks the process's setting once: the files load. Servers call it when
/// they start, and behaviorctl before it dials.
absl::Status checkProcessTransport();

/// mTLS server credentials (client certificate required and verified), or
/// insecure ones without TLS.
absl::StatusOr<std::shared_ptr<grpc::ServerCredentials>> serverCredentials(
    const TransportSecurity& security);
/// TLS client credentials with this process's certificate, or insecure ones.
absl::StatusOr<std::shared_ptr<grpc::ChannelCredentials>> channelCredentials(
    const TransportSecurity& security);

/// True for 127.0.0.0/8, ::1, localhost and unix sockets.
bool isLoopbackAddress(const std::string& address);

/// INVALID_ARGUMENT when `address` (a --listen value) is not loopback, has
/// no TLS and is not --insecure; the message says what that would risk.
absl::Status checkListenAddress(const std::string& address, const TransportSecurity& security,
                                const std::string& flag = "--listen");

/// A channel to `target` with the process's credentials. If the process's
/// TLS files cannot be loaded (checkProcessTransport() was not called, or
/// they changed), the channel refuses every call: it never falls back to
/// plaintext.
std::shared_ptr<grpc::Channel> makeChannel(const std::string& target,
                                           const grpc::ChannelArguments& args = {});

}  // namespace behaviorlib::server_kit
