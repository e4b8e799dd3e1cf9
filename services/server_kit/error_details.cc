#include "behaviorlib/error_details.h"

#include <google/protobuf/any.pb.h>

#include "absl/strings/cord.h"
#include "absl/strings/match.h"
#include "google/rpc/status.pb.h"

namespace behaviorlib::errors {

namespace {

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
    if (!absl::StartsWith(url, kTypeUrlPrefix) || url == typeUrl<google::rpc::ErrorInfo>()) return;
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
    if (absl::StartsWith(any.type_url(), kTypeUrlPrefix)) {
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
