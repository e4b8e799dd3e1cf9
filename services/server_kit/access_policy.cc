#include "behaviorlib/server_kit/access_policy.h"

#include <openssl/crypto.h>
#include <openssl/evp.h>

#include <algorithm>
#include <array>
#include <cctype>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/confined_files.h"
#include "behaviorlib/server_kit/yaml_guard.h"

namespace behaviorlib::server_kit {
namespace {

constexpr std::array<std::pair<Role, std::string_view>, 5> kRoleNames = {{
    {Role::kViewer, "viewer"},
    {Role::kOperator, "operator"},
    {Role::kSafety, "safety"},
    {Role::kSystem, "system"},
    {Role::kAdmin, "admin"},
}};

// The policy callerOf() reads (ServerRuntime sets it with the authorizer's).
absl::Mutex policy_mutex;
std::shared_ptr<const AccessPolicy>& processPolicy() ABSL_EXCLUSIVE_LOCKS_REQUIRED(policy_mutex) {
  static auto* policy = new std::shared_ptr<const AccessPolicy>();
  return *policy;
}

// A client certificate's names, in the order identify() tries them. The
// AuthContext belongs to the connection, not the call: nothing is added to
// it (properties added per call would pile up for the connection's life).
std::vector<std::string> certificateNames(const grpc::AuthContext& context) {
  std::vector<std::string> names;
  for (const char* property : {"peer_uri", "peer_dns", "x509_common_name"}) {
    for (const auto& value : context.FindPropertyValues(property)) {
      names.emplace_back(value.data(), value.size());
    }
  }
  return names;
}

// How logs and messages name a caller.
std::string callerName(const Identity* identity, const std::vector<std::string>& names) {
  if (identity != nullptr) return identity->name;
  return names.empty() ? std::string("anonymous") : names.front();
}

std::string bearerToken(std::string_view authorization) {
  return absl::StartsWithIgnoreCase(absl::string_view(authorization.data(), authorization.size()),
                                    "bearer ")
             ? std::string(authorization.substr(7))
             : std::string();
}

// Debian's absl::string_view is its own type, not std::string_view.
absl::string_view av(std::string_view s) { return absl::string_view(s.data(), s.size()); }

std::string sha256Hex(std::string_view text) {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  EVP_Digest(text.data(), text.size(), digest, &length, EVP_sha256(), nullptr);
  static constexpr char kHex[] = "0123456789abcdef";
  std::string out;
  for (unsigned int i = 0; i < length; ++i) {
    out += kHex[digest[i] >> 4];
    out += kHex[digest[i] & 0xf];
  }
  return out;
}

std::string rolesText(const std::set<Role>& roles) {
  std::vector<absl::string_view> names;
  for (Role r : roles) names.push_back(av(roleName(r)));
  return names.empty() ? "no role" : absl::StrJoin(names, ", ");
}

class Authorizer final : public grpc::AuthMetadataProcessor {
 public:
  Authorizer(std::shared_ptr<const AccessPolicy> policy, AuditSink audit)
      : policy_(std::move(policy)), audit_(std::move(audit)) {}

  bool IsBlocking() const override { return false; }

  grpc::Status Process(const InputMetadata& metadata, grpc::AuthContext* context, OutputMetadata*,
                       OutputMetadata*) override {
    if (!policy_) return grpc::Status::OK;
    std::string method;
    std::string token;
    for (const auto& [key, value] : metadata) {
      const std::string_view k(key.data(), key.size());
      if (k == ":path") method.assign(value.data(), value.size());
      // Left in the metadata: callerOf() identifies the caller again from it.
      if (k == "authorization") token = bearerToken(std::string_view(value.data(), value.size()));
    }
    const std::vector<std::string> names = certificateNames(*context);
    const Identity* identity = policy_->identify(names, token);
    const std::string who = callerName(identity, names);
    const Role needed = requiredRole(method);
    if (identity == nullptr || identity->roles.count(needed) == 0) {
      const std::string message =
          identity == nullptr ? absl::StrCat(method, " needs the role ", av(roleName(needed)),
                                             "; '", who, "' is not in the access policy")
                              : absl::StrCat(method, " needs the role ", av(roleName(needed)),
                                             "; '", who, "' has ", rolesText(identity->roles));
      if (audit_) audit_({who, method, "PERMISSION_DENIED", message});
      // Note: gRPC's auth filter hands on only the code and the message of a
      // processor's refusal (grpc_process_auth_metadata_done_cb takes no
      // details), so the client may receive this one without its ErrorInfo.
      return errors::grpcError(grpc::StatusCode::PERMISSION_DENIED, v1::ROLE_REQUIRED, message,
                               {{"role", std::string(roleName(needed))}, {"identity", who}});
    }
    return grpc::Status::OK;
  }

 private:
  const std::shared_ptr<const AccessPolicy> policy_;
  const AuditSink audit_;
};

}  // namespace

std::string_view roleName(Role role) {
  for (const auto& [r, name] : kRoleNames) {
    if (r == role) return name;
  }
  return "unknown";
}

Role requiredRole(std::string_view method) {
  const size_t slash = method.rfind('/');
  const std::string_view service = method.substr(0, slash == std::string_view::npos ? 0 : slash);
  const std::string_view name = slash == std::string_view::npos ? method : method.substr(slash + 1);
  if (absl::StartsWith(av(service), "/grpc.health.") ||
      absl::StartsWith(av(service), "/grpc.reflection.")) {
    return Role::kViewer;
  }
  if (service == "/behaviorlib.v1.Simulator" &&
      (name == "Reset" || name == "SetTimeScale" || name == "Step" || name == "InjectFailure")) {
    return Role::kAdmin;
  }
  if (name == "RegisterSystem" || name == "Heartbeat" || name == "UnregisterSystem" ||
      name == "FollowTime") {
    return Role::kSystem;
  }
  if (name == "EmergencyLand" || name == "Kill") return Role::kSafety;
  for (std::string_view prefix : {"List", "Watch", "Check", "Get", "Read", "Subscribe"}) {
    if (absl::StartsWith(av(name), av(prefix))) return Role::kViewer;
  }
  return Role::kOperator;
}

absl::StatusOr<AccessPolicy> AccessPolicy::parse(std::string_view yaml, const std::string& file) {
  YAML::Node root;
  if (absl::Status s = loadYaml(yaml, file, &root); !s.ok()) return s;
  AccessPolicy policy;
  auto error = [&](const YAML::Node& node, const std::string& what) {
    const int line = node.Mark().is_null() ? 1 : node.Mark().line + 1;
    return absl::InvalidArgumentError(absl::StrCat(file, ":", line, ": ", what));
  };
  absl::Status parsed = guardYamlParse(file, [&]() -> absl::Status {
    if (!root.IsMap() || !root["identities"] || !root["identities"].IsSequence()) {
      return error(root, "an access policy is a mapping with a list 'identities'");
    }
    for (const auto& key : root) {
      if (key.first.Scalar() != "identities") {
        return error(key.first, "unknown key '" + key.first.Scalar() + "' (expected identities)");
      }
    }
    for (const YAML::Node& item : root["identities"]) {
      if (!item.IsMap()) return error(item, "an identity is a mapping");
      Entry entry;
      for (const auto& key : item) {
        const std::string k = key.first.Scalar();
        if (k != "certificate" && k != "token_sha256" && k != "name" && k != "roles" &&
            k != "system" && k != "robot") {
          return error(key.first, "unknown key '" + k +
                                      "' (expected certificate or token_sha256, name, roles, "
                                      "system, robot)");
        }
      }
      if (item["certificate"]) entry.certificate = item["certificate"].as<std::string>();
      if (item["token_sha256"]) {
        entry.token_sha256 = absl::AsciiStrToLower(item["token_sha256"].as<std::string>());
        const bool hex = entry.token_sha256.size() == 64 &&
                         std::all_of(entry.token_sha256.begin(), entry.token_sha256.end(),
                                     [](char c) { return std::isxdigit(c) != 0; });
        if (!hex) return error(item["token_sha256"], "token_sha256 must be 64 hex digits");
      }
      if (entry.certificate.empty() == entry.token_sha256.empty()) {
        return error(item, "an identity has either a certificate or a token_sha256");
      }
      entry.identity.name = item["name"]                ? item["name"].as<std::string>()
                            : entry.certificate.empty() ? "token " + entry.token_sha256.substr(0, 8)
                                                        : entry.certificate;
      if (!item["roles"] || !item["roles"].IsSequence() || item["roles"].size() == 0) {
        return error(item, "an identity needs a list of roles");
      }
      for (const YAML::Node& r : item["roles"]) {
        const std::string name = r.as<std::string>();
        bool known = false;
        for (const auto& [role, role_name] : kRoleNames) {
          if (name == role_name) {
            entry.identity.roles.insert(role);
            known = true;
          }
        }
        if (!known) {
          return error(
              r, "unknown role '" + name + "' (expected viewer, operator, safety, system, admin)");
        }
      }
      if (const YAML::Node system = item["system"]) {
        if (!system.IsMap() || !system["robot"] || !system["name"]) {
          return error(system, "system: {robot: ROBOT_ID, name: SYSTEM}");
        }
        entry.identity.robot_id = system["robot"].as<std::string>();
        entry.identity.system = system["name"].as<std::string>();
      }
      if (const YAML::Node robot = item["robot"]) {
        const std::string id = robot.IsScalar() ? robot.Scalar() : std::string();
        if (id.empty()) return error(robot, "robot: ROBOT_ID, the one robot it may command");
        if (!entry.identity.robot_id.empty() && entry.identity.robot_id != id) {
          return error(robot, "robot '" + id + "' is not the system's robot '" +
                                  entry.identity.robot_id + "'");
        }
        entry.identity.robot_id = id;
      }
      if (entry.identity.roles.count(Role::kSystem) != 0 && entry.identity.system.empty()) {
        return error(item,
                     "the system role needs system: {robot, name}, the system it may register as");
      }
      policy.identities_.push_back(std::move(entry));
    }
    return absl::OkStatus();
  });
  if (!parsed.ok()) return parsed;
  return policy;
}

absl::StatusOr<AccessPolicy> AccessPolicy::load(const std::string& path) {
  absl::StatusOr<std::string> text = readFileCapped(path, 1 << 20);
  if (!text.ok()) return text.status();
  return parse(*text, path);
}

const Identity* AccessPolicy::identify(const std::vector<std::string>& certificate_names,
                                       std::string_view bearer_token) const {
  if (!bearer_token.empty()) {
    const std::string hash = sha256Hex(bearer_token);
    for (const Entry& e : identities_) {
      if (e.token_sha256.size() == hash.size() &&
          CRYPTO_memcmp(e.token_sha256.data(), hash.data(), hash.size()) == 0) {
        return &e.identity;
      }
    }
    return nullptr;  // a wrong token is not made good by the certificate
  }
  for (const std::string& name : certificate_names) {
    for (const Entry& e : identities_) {
      if (!e.certificate.empty() && e.certificate == name) return &e.identity;
    }
  }
  return nullptr;
}

std::shared_ptr<grpc::AuthMetadataProcessor> makeAuthorizer(
    std::shared_ptr<const AccessPolicy> policy, AuditSink audit) {
  return std::make_shared<Authorizer>(std::move(policy), std::move(audit));
}

void setProcessAccessPolicy(std::shared_ptr<const AccessPolicy> policy) {
  absl::MutexLock lock(&policy_mutex);
  processPolicy() = std::move(policy);
}

std::optional<Caller> callerOf(const grpc::ServerContextBase& context) {
  std::shared_ptr<const AccessPolicy> policy;
  {
    absl::MutexLock lock(&policy_mutex);
    policy = processPolicy();
  }
  const std::shared_ptr<const grpc::AuthContext> auth = context.auth_context();
  const std::vector<std::string> names =
      auth ? certificateNames(*auth) : std::vector<std::string>();
  if (!policy && names.empty()) return std::nullopt;
  std::string token;
  const auto& metadata = context.client_metadata();
  if (auto it = metadata.find("authorization"); it != metadata.end()) {
    token = bearerToken(std::string_view(it->second.data(), it->second.size()));
  }
  const Identity* identity = policy ? policy->identify(names, token) : nullptr;
  Caller caller;
  caller.identity = callerName(identity, names);
  caller.policy = policy != nullptr;
  if (identity != nullptr) {
    caller.roles = identity->roles;
    caller.robot_id = identity->robot_id;
    caller.system = identity->system;
  }
  return caller;
}

absl::Status checkSystemIdentity(const grpc::ServerContextBase& context,
                                 const std::string& robot_id, const std::string& system) {
  const std::optional<Caller> caller = callerOf(context);
  if (!caller || !caller->policy || caller->roles.count(Role::kAdmin) != 0) {
    return absl::OkStatus();
  }
  if (caller->robot_id != robot_id || caller->system != system) {
    return errors::withReason(
        absl::PermissionDeniedError(absl::StrCat(
            "'", caller->identity, "' may register only as system ", caller->system, " of robot ",
            caller->robot_id, ", not as ", system, " of robot ", robot_id)),
        v1::IDENTITY_MISMATCH,
        {{"identity", caller->identity}, {"robot", robot_id}, {"system", system}});
  }
  return absl::OkStatus();
}

absl::Status RobotScope::permits(std::string_view robot_id, std::string_view what) const {
  if (!bound() || robot_id == robot_id_) return absl::OkStatus();
  return errors::withReason(
      absl::PermissionDeniedError(absl::StrCat("'", identity_, "' may ", av(what),
                                               " only for robot ", robot_id_, ", not for robot '",
                                               av(robot_id), "'")),
      v1::ROBOT_NOT_PERMITTED,
      {{"identity", identity_}, {"robot", std::string(robot_id)}, {"allowed_robot", robot_id_}});
}

absl::Status RobotScope::permitsTopic(std::string_view topic,
                                      std::string_view shared_prefix) const {
  if (!bound()) return absl::OkStatus();
  const std::string prefix = absl::StrCat("robots/", robot_id_, "/");
  if (absl::StartsWith(av(topic), prefix) ||
      (!shared_prefix.empty() && absl::StartsWith(av(topic), av(shared_prefix)))) {
    return absl::OkStatus();
  }
  // The robot the topic names, for the details (empty: none).
  std::string named;
  if (absl::StartsWith(av(topic), "robots/")) {
    const std::string_view rest = topic.substr(7);
    named = std::string(rest.substr(0, rest.find('/')));
  }
  return errors::withReason(
      absl::PermissionDeniedError(absl::StrCat("'", identity_, "' may publish only under ", prefix,
                                               shared_prefix.empty() ? "" : " or ",
                                               av(shared_prefix), ", not on '", av(topic), "'")),
      v1::ROBOT_NOT_PERMITTED,
      {{"identity", identity_},
       {"robot", named},
       {"allowed_robot", robot_id_},
       {"topic", std::string(topic)}});
}

RobotScope robotScopeOf(const grpc::ServerContextBase& context) {
  const std::optional<Caller> caller = callerOf(context);
  if (!caller || !caller->policy) return RobotScope();
  return RobotScope(caller->identity, caller->robot_id);
}

absl::Status checkRobotScope(const grpc::ServerContextBase& context, std::string_view robot_id,
                             std::string_view what) {
  return robotScopeOf(context).permits(robot_id, what);
}

}  // namespace behaviorlib::server_kit
