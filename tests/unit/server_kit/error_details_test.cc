// error_details.h: reasons, metadata and field violations on absl::Status,
// and their trip through grpc::Status (grpc-status-details-bin).

#include "behaviorlib/error_details.h"

#include <gtest/gtest.h>

#include "google/rpc/status.pb.h"

namespace behaviorlib::errors {
namespace {

TEST(ErrorDetails, ReasonAndMetadataTravelThroughGrpcStatus) {
  absl::Status status = withReason(absl::FailedPreconditionError("TAKE_OFF is already active"),
                                   v1::BEHAVIOR_ALREADY_ACTIVE,
                                   {{"behavior", "TAKE_OFF"}, {"current_activation_id", "a-1"}});
  const grpc::Status wire = toGrpc(status);
  EXPECT_EQ(wire.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_EQ(wire.error_message(), "TAKE_OFF is already active");

  // The trailer is a google.rpc.Status with the same code and message.
  google::rpc::Status details;
  ASSERT_TRUE(details.ParseFromString(wire.error_details()));
  EXPECT_EQ(details.code(), static_cast<int>(grpc::StatusCode::FAILED_PRECONDITION));
  EXPECT_EQ(details.message(), "TAKE_OFF is already active");
  ASSERT_EQ(details.details_size(), 1);
  google::rpc::ErrorInfo info;
  ASSERT_TRUE(details.details(0).UnpackTo(&info));
  EXPECT_EQ(info.reason(), "BEHAVIOR_ALREADY_ACTIVE");
  EXPECT_EQ(info.domain(), "behaviorlib.v1");
  EXPECT_EQ(info.metadata().at("behavior"), "TAKE_OFF");
  EXPECT_EQ(info.metadata().at("current_activation_id"), "a-1");

  // And back: a relaying server keeps them.
  const absl::Status relayed = fromGrpc(wire);
  EXPECT_EQ(relayed.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(reasonOf(relayed), "BEHAVIOR_ALREADY_ACTIVE");
}

TEST(ErrorDetails, EveryErrorCarriesAnErrorInfo) {
  const grpc::Status wire = toGrpc(absl::InternalError("something broke"));
  auto info = errorInfo(wire);
  ASSERT_TRUE(info.has_value());
  EXPECT_EQ(info->reason(), "ERROR_REASON_UNSPECIFIED");
  EXPECT_EQ(info->domain(), "behaviorlib.v1");
  EXPECT_TRUE(toGrpc(absl::OkStatus()).ok());
  EXPECT_TRUE(toGrpc(absl::OkStatus()).error_details().empty());
  // INVALID_ARGUMENT without a finer reason: a request field is wrong.
  EXPECT_EQ(errorInfo(toGrpc(absl::InvalidArgumentError("x must be finite")))->reason(),
            "INVALID_REQUEST");
  EXPECT_EQ(errorInfo(toGrpc(withReason(absl::InvalidArgumentError("bad"), v1::MISSION_INVALID)))
                ->reason(),
            "MISSION_INVALID");
}

TEST(ErrorDetails, TheAccessPolicysRefusalIsRebuiltFromItsMessage) {
  // gRPC's auth filter delivers it with no details (ROLE_REQUIRED).
  const absl::Status known = fromGrpc(grpc::Status(
      grpc::StatusCode::PERMISSION_DENIED,
      "/behaviorlib.v1.Coordinator/Kill needs the role safety; 'behaviorlib:operator' has "
      "viewer, operator"));
  EXPECT_EQ(known.code(), absl::StatusCode::kPermissionDenied);
  ASSERT_TRUE(errorInfo(known).has_value());
  EXPECT_EQ(reasonOf(known), "ROLE_REQUIRED");
  EXPECT_EQ(errorInfo(known)->metadata().at("role"), "safety");
  EXPECT_EQ(errorInfo(known)->metadata().at("identity"), "behaviorlib:operator");
  const absl::Status stranger = fromGrpc(
      grpc::Status(grpc::StatusCode::PERMISSION_DENIED,
                   "/behaviorlib.v1.Simulator/Reset needs the role admin; 'it's me' is not in "
                   "the access policy"));
  EXPECT_EQ(errorInfo(stranger)->metadata().at("identity"), "it's me");
  // Other refusals, and other codes with that wording, are left alone.
  EXPECT_FALSE(
      errorInfo(fromGrpc(grpc::Status(grpc::StatusCode::PERMISSION_DENIED, "no"))).has_value());
  EXPECT_FALSE(errorInfo(fromGrpc(grpc::Status(grpc::StatusCode::INTERNAL,
                                               "/x/Y needs the role safety; 'a' has viewer")))
                   .has_value());
}

TEST(ErrorDetails, FieldViolationsArePrefixedAndKept) {
  absl::Status status = absl::InvalidArgumentError("parameter 'altitude_m' = 100 is out of range");
  status = withFieldViolation(status, "altitude_m", "100 is out of range [0.2, 10]");
  status = withFieldViolation(status, "", "the whole message");
  status = prefixFieldViolations(status, "parameters.", "mission.yaml:4: ");
  status = withReason(status, v1::PARAMETER_OUT_OF_RANGE);

  auto bad = badRequest(toGrpc(status));
  ASSERT_TRUE(bad.has_value());
  ASSERT_EQ(bad->field_violations_size(), 2);
  EXPECT_EQ(bad->field_violations(0).field(), "parameters.altitude_m");
  EXPECT_EQ(bad->field_violations(0).description(),
            "mission.yaml:4: 100 is out of range [0.2, 10]");
  // An empty path under a prefix names the prefix itself.
  EXPECT_EQ(bad->field_violations(1).field(), "parameters");
  EXPECT_EQ(errorInfo(toGrpc(status))->reason(), "PARAMETER_OUT_OF_RANGE");
}

TEST(ErrorDetails, DefaultReasonDoesNotReplaceAFinerOne) {
  absl::Status status = withReason(absl::InvalidArgumentError("x"), v1::PARAMETER_OUT_OF_RANGE);
  status = withDefaultReason(status, v1::PARAMETER_INVALID, {{"behavior", "WAIT"}});
  EXPECT_EQ(reasonOf(status), "PARAMETER_OUT_OF_RANGE");
  EXPECT_EQ(errorInfo(status)->metadata().at("behavior"), "WAIT");
  // Metadata already there keeps its value.
  status = withMetadata(status, {{"behavior", "LAND"}, {"robot", "drone1"}});
  EXPECT_EQ(errorInfo(status)->metadata().at("behavior"), "WAIT");
  EXPECT_EQ(errorInfo(status)->metadata().at("robot"), "drone1");
  // withReason replaces.
  status = withReason(status, v1::INVALID_REQUEST);
  EXPECT_EQ(reasonOf(status), "INVALID_REQUEST");
}

TEST(ErrorDetails, RewrapKeepsDetailsUnderANewMessage) {
  absl::Status inner = withFieldViolation(
      withReason(absl::InvalidArgumentError("inner"), v1::PARAMETER_INVALID), "duration_s", "bad");
  absl::Status outer = rewrap(inner, "robot drone1, system s at a:1: inner");
  EXPECT_EQ(outer.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(outer.message(), "robot drone1, system s at a:1: inner");
  EXPECT_EQ(reasonOf(outer), "PARAMETER_INVALID");
  ASSERT_TRUE(badRequest(outer).has_value());
  EXPECT_EQ(badRequest(outer)->field_violations(0).field(), "duration_s");
  EXPECT_EQ(rewrap(inner, absl::StatusCode::kAborted, "x").code(), absl::StatusCode::kAborted);
}

TEST(ErrorDetails, GrpcErrorAndPeersWithoutDetails) {
  const grpc::Status refused = grpcError(grpc::StatusCode::PERMISSION_DENIED, v1::ROLE_REQUIRED,
                                         "needs role operator", {{"role", "operator"}});
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::PERMISSION_DENIED);
  EXPECT_EQ(errorInfo(refused)->reason(), "ROLE_REQUIRED");
  EXPECT_EQ(errorInfo(refused)->metadata().at("role"), "operator");
  // A peer that sent no details (gRPC's own errors), or garbage.
  const absl::Status plain = fromGrpc(grpc::Status(grpc::StatusCode::UNAVAILABLE, "down"));
  EXPECT_EQ(plain.code(), absl::StatusCode::kUnavailable);
  EXPECT_FALSE(errorInfo(plain).has_value());
  const absl::Status garbage =
      fromGrpc(grpc::Status(grpc::StatusCode::UNAVAILABLE, "down", "\xff\xff not a proto"));
  EXPECT_EQ(garbage.message(), "down");
  EXPECT_FALSE(errorInfo(garbage).has_value());
}

}  // namespace
}  // namespace behaviorlib::errors
