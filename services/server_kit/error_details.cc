#include "behaviorlib/error_details.h"

#include <google/protobuf/any.pb.h>

#include "absl/strings/cord.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "google/rpc/status.pb.h"

namespace behaviorlib::errors {

namespace {

constexpr char kTypePrefix[] = "type.googleapis.com/";

template <typename Message>
std::string typeUrl() {
  return absl::StrCat(kTypePrefix, Message::descriptor()->full_name());
}

template <typename Message>
std::optional<Message> payload(const absl::Status& status) {
  auto cord = status.GetPayload(typeUrl<Message>());
  if (!cord) return std::nullopt;
  Message message;
  if (!message.ParseFromString(std::string(*cord))) return std::nullopt;
  return message;
}

template <typename Message>
void setPayload(absl::Status& status, const Message& message) {
  status.SetPayload(typeUrl<Message>(), absl::Cord(message.SerializeAsString()));
}

google::rpc::ErrorInfo infoOf(const absl::Status& status) {
  auto info = payload<google::rpc::ErrorInfo>(status);
  if (info) return *info;
  google::rpc::ErrorInfo fresh;
  fresh.set_domain(std::string(kDomain));
  return fresh;
}

void addMetadata(google::rpc::ErrorInfo& info, const Metadata& metadata) {
  for (const auto& [key, value] : metadata) info.mutable_metadata()->insert({key, value});
}

absl::Status setReason(absl::Status status, v1::ErrorReason reason, const Metadata& metadata,
                       bool replace) {
  if (status.ok()) return status;
  google::rpc::ErrorInfo info = infoOf(status);
  if (replace || info.reason().empty() ||
      info.reason() == v1::ErrorReason_Name(v1::ERROR_REASON_UNSPECIFIED)) {
    info.set_reason(v1::ErrorReason_Name(reason));
  }
  addMetadata(info, metadata);
  setPayload(status, info);
  return status;
}

// The access policy refuses a call in gRPC's AuthMetadataProcessor, which
// hands on only the code and the message, so that refusal arrives without
// details. Its message has a stable form, "<method> needs the role <role>;
// '<identity>' ...": the ErrorInfo is rebuilt from it (ROLE_REQUIRED in
// errors.proto).
absl::Status withPolicyRefusalInfo(absl::Status status) {
  if (status.code() != absl::StatusCode::kPermissionDenied) return status;
  const absl::string_view message = status.message();
  constexpr absl::string_view kNeeds = " needs the role ";
  const size_t needs = message.find(kNeeds);
  if (needs == absl::string_view::npos) return status;
  const size_t role_start = needs + kNeeds.size();
  const size_t role_end = message.find("; '", role_start);
  if (role_end == absl::string_view::npos) return status;
  const size_t who_start = role_end + 3;
  const size_t who_end = message.rfind('\'');
  if (who_end == absl::string_view::npos || who_end < who_start) return status;
  return withReason(std::move(status), v1::ROLE_REQUIRED,
                    {{"role", std::string(message.substr(role_start, role_end - role_start))},
                     {"identity", std::string(message.substr(who_start, who_end - who_start))}});
}

}  // namespace

absl::Status withReason(absl::Status status, v1::ErrorReason reason, const Metadata& metadata) {
  return setReason(std::move(status), reason, metadata, true);
}

absl::Status withDefaultReason(absl::Status status, v1::ErrorReason reason,
                               const Metadata& metadata) {
  return setReason(std::move(status), reason, metadata, false);
}

absl::Status withMetadata(absl::Status status, const Metadata& metadata) {
  if (status.ok()) return status;
  google::rpc::ErrorInfo info = infoOf(status);
  addMetadata(info, metadata);
  setPayload(status, info);
  return status;
}

absl::Status withFieldViolation(absl::Status status, absl::string_view field,
                                absl::string_view description) {
  if (status.ok()) return status;
  google::rpc::BadRequest bad =
      payload<google::rpc::BadRequest>(status).value_or(google::rpc::BadRequest());
  auto* violation = bad.add_field_violations();
  violation->set_field(std::string(field));
  violation->set_description(std::string(description));
  setPayload(status, bad);
  return status;
}

absl::Status prefixFieldViolations(absl::Status status, absl::string_view prefix,
                                   absl::string_view description_prefix) {
  auto bad = payload<google::rpc::BadRequest>(status);
  if (!bad) return status;
  for (auto& violation : *bad->mutable_field_violations()) {
    std::string field = absl::StrCat(prefix, violation.field());
    // "steps[2]." + "" -> "steps[2]"; "steps[2]." + "[0]" stays as written.
    if (violation.field().empty() && absl::EndsWith(field, ".")) field.pop_back();
    violation.set_field(std::move(field));
    violation.set_description(absl::StrCat(description_prefix, violation.description()));
  }
  setPayload(status, *bad);
  return status;
}

absl::Status rewrap(const absl::Status& from, absl::StatusCode code, std::string message) {
  absl::Status to(code, message);
  if (to.ok()) return to;
  from.ForEachPayload(
      [&](absl::string_view url, const absl::Cord& value) { to.SetPayload(url, value); });
  return to;
}

absl::Status rewrap(const absl::Status& from, std::string message) {
  return rewrap(from, from.code(), std::move(message));
}

std::optional<google::rpc::ErrorInfo> errorInfo(const absl::Status& status) {
  return payload<google::rpc::ErrorInfo>(status);
}

std::optional<google::rpc::BadRequest> badRequest(const absl::Status& status) {
  return payload<google::rpc::BadRequest>(status);
}

std::string reasonOf(const absl::Status& status) {
  auto info = errorInfo(status);
  return info ? info->reason() : std::string();
}

grpc::Status toGrpc(const absl::Status& status) {
  if (status.ok()) return grpc::Status::OK;
  // INVALID_ARGUMENT says a request field is wrong; other codes have no
  // reason finer than themselves.
  absl::Status with_info = withDefaultReason(
      status, status.code() == absl::StatusCode::kInvalidArgument ? v1::INVALID_REQUEST
                                                                  : v1::ERROR_REASON_UNSPECIFIED);
  google::rpc::Status details;
  details.set_code(static_cast<int>(status.code()));
  details.set_message(std::string(status.message()));
  // ErrorInfo first: clients that show one detail show the reason.
  auto info = errorInfo(with_info);
  details.add_details()->PackFrom(*info);
  with_info.ForEachPayload([&](absl::string_view url, const absl::Cord& value) {
    if (!absl::StartsWith(url, kTypePrefix) || url == typeUrl<google::rpc::ErrorInfo>()) return;
    auto* any = details.add_details();
    any->set_type_url(std::string(url));
    any->set_value(std::string(value));
  });
  return grpc::Status(static_cast<grpc::StatusCode>(status.code()), std::string(status.message()),
                      details.SerializeAsString());
}

absl::Status fromGrpc(const grpc::Status& status) {
  if (status.ok()) return absl::OkStatus();
  absl::Status result(static_cast<absl::StatusCode>(status.error_code()), status.error_message());
  google::rpc::Status details;
  if (status.error_details().empty() || !details.ParseFromString(status.error_details())) {
    return withPolicyRefusalInfo(std::move(result));
  }
  for (const auto& any : details.details()) {
    if (absl::StartsWith(any.type_url(), kTypePrefix)) {
      result.SetPayload(any.type_url(), absl::Cord(any.value()));
    }
  }
  return result;
}

grpc::Status grpcError(grpc::StatusCode code, v1::ErrorReason reason, std::string message,
                       const Metadata& metadata) {
  return toGrpc(
      withReason(absl::Status(static_cast<absl::StatusCode>(code), message), reason, metadata));
}

std::optional<google::rpc::ErrorInfo> errorInfo(const grpc::Status& status) {
  return errorInfo(fromGrpc(status));
}

std::optional<google::rpc::BadRequest> badRequest(const grpc::Status& status) {
  return badRequest(fromGrpc(status));
}

}  // namespace behaviorlib::errors
