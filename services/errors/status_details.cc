#include "behaviorlib/errors/status_details.h"

#include "absl/strings/cord.h"
#include "absl/strings/match.h"

namespace behaviorlib::errors {

namespace {

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

}  // namespace behaviorlib::errors
