#pragma once

// Roles: who may call what, on every server of behaviorlib.
//
// A policy file (--access-policy FILE, YAML) maps identities to roles:
//
//   identities:
//     - certificate: behaviorlib:operator        # a client certificate's name:
//       roles: [viewer, operator, safety]        #   URI or DNS SAN, or its CN
//     - certificate: behaviorlib:drone1-navigation-with-lidar
//       roles: [viewer, operator, system]
//       system: {robot: drone1, name: navigation_with_lidar}
//     - certificate: behaviorlib:drone1-tablet     # an operator of one robot
//       roles: [viewer, operator]
//       robot: drone1
//     - token_sha256: 5e884898da28...            # a bearer token, by its SHA-256
//       name: dashboard                          #   (authorization: Bearer <token>)
//       roles: [viewer]
//
// Each method needs one role (requiredRole): viewer for List, Watch, Check,
// Get, Read, Subscribe, health and reflection; safety for EmergencyLand and
// Kill; system for RegisterSystem, Heartbeat, UnregisterSystem and FollowTime;
// admin for the simulator's Reset, SetTimeScale, Step and InjectFailure;
// operator for everything else (activate, deactivate, missions, beliefs,
// publishing, flight commands). A call from an identity without that role,
// or from no known identity, is PERMISSION_DENIED naming the role.
//
// An identity bound to a robot (`system: {robot}` or `robot:`) commands only
// that robot: the handlers that take a robot (the coordinator's behavior
// calls and StartMission, the simulator's flight controller and FollowTime,
// a behavior system's lifecycle calls, the channel's Publish of robots/<id>/
// topics) refuse another with ROBOT_NOT_PERMITTED (RobotScope). It still
// reads all it may view.
//
// The policy is enforced by gRPC's AuthMetadataProcessor on the TLS
// credentials (transport_security.h), before any handler runs; it needs
// TLS. A handler finds who called with callerOf() (RegisterSystem checks
// that a system registers as itself). The processor writes nothing into the
// auth context: gRPC hands it the connection's, where a property added per
// call would stay for the connection's life.

#include <grpcpp/grpcpp.h>
#include <grpcpp/security/auth_metadata_processor.h>

#include <functional>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace behaviorlib::server_kit {

enum class Role { kViewer, kOperator, kSafety, kSystem, kAdmin };

std::string_view roleName(Role role);
/// The role that `method` ("/package.Service/Method") needs.
Role requiredRole(std::string_view method);

struct Identity {
  std::string name;  ///< the certificate name or the token's name, for logs
  std::set<Role> roles;
  /// The only robot it may command (and, for the system role, register
  /// for); empty: any robot.
  std::string robot_id;
  std::string system;
};

class AccessPolicy {
 public:
  /// INVALID_ARGUMENT naming the file and line.
  static absl::StatusOr<AccessPolicy> parse(std::string_view yaml, const std::string& file);
  static absl::StatusOr<AccessPolicy> load(const std::string& path);

  /// The identity of a caller from its bearer token (when it sends one) or
  /// the names of its certificate (URI and DNS SANs, then CN); null when
  /// the policy knows none of them.
  const Identity* identify(const std::vector<std::string>& certificate_names,
                           std::string_view bearer_token) const;
  size_t size() const { return identities_.size(); }

 private:
  struct Entry {
    std::string certificate;   // or
    std::string token_sha256;  // lower-case hex
    Identity identity;
  };
  std::vector<Entry> identities_;
};

/// One control call, or a refusal, for the audit log.
struct AuditRecord {
  std::string identity;  ///< who ("anonymous" without one)
  std::string method;    ///< "/package.Service/Method"
  std::string outcome;   ///< "OK", "PERMISSION_DENIED", ... (the gRPC code)
  std::string message;   ///< the status message, if any
};
using AuditSink = std::function<void(const AuditRecord&)>;

/// The processor that enforces `policy` (null: every authenticated peer may
/// call anything, and only its identity is recorded). Refusals go to
/// `audit` when set.
std::shared_ptr<grpc::AuthMetadataProcessor> makeAuthorizer(
    std::shared_ptr<const AccessPolicy> policy, AuditSink audit);

/// The policy that callerOf() identifies callers with; ServerRuntime sets
/// the one it enforces (null: none).
void setProcessAccessPolicy(std::shared_ptr<const AccessPolicy> policy);

/// The caller of a call, identified as the authorizer did (its certificate,
/// or the bearer token it sends).
struct Caller {
  std::string identity;
  std::set<Role> roles;
  std::string robot_id;  ///< the robot it is bound to (RobotScope), if any
  std::string system;
  bool policy = false;  ///< roles come from an access policy
};
/// Null for a plaintext call when no policy is in force.
std::optional<Caller> callerOf(const grpc::ServerContextBase& context);

/// For RegisterSystem and Heartbeat: PERMISSION_DENIED when a policy is in
/// force and the caller's identity does not name this robot and system.
absl::Status checkSystemIdentity(const grpc::ServerContextBase& context,
                                 const std::string& robot_id, const std::string& system);

/// The one robot a caller may command. An identity is bound to a robot by
/// its `system: {robot: ...}` (every behavior system's certificate) or by
/// `robot: ROBOT_ID`; any other caller, and every caller when no policy is
/// in force, is unbound. Resolve it once per call or stream (callerOf
/// hashes and searches), then ask it per request.
class RobotScope {
 public:
  RobotScope() = default;
  RobotScope(std::string identity, std::string robot_id)
      : identity_(std::move(identity)), robot_id_(std::move(robot_id)) {}

  bool bound() const { return !robot_id_.empty(); }
  const std::string& robot() const { return robot_id_; }

  /// PERMISSION_DENIED (ROBOT_NOT_PERMITTED) when bound to another robot
  /// than `robot_id`. `what` names the call in the message ("activate
  /// TAKE_OFF", "command the vehicle").
  absl::Status permits(std::string_view robot_id, std::string_view what) const;
  /// For publishing: a bound caller publishes only robots/<its robot>/...
  /// and, when given, under `shared_prefix` (topics every robot publishes).
  absl::Status permitsTopic(std::string_view topic, std::string_view shared_prefix = {}) const;

 private:
  std::string identity_;
  std::string robot_id_;
};

RobotScope robotScopeOf(const grpc::ServerContextBase& context);
/// robotScopeOf(context).permits(robot_id, what).
absl::Status checkRobotScope(const grpc::ServerContextBase& context, std::string_view robot_id,
                             std::string_view what);

}  // namespace behaviorlib::server_kit
