#pragma once

// BeliefClient: how behaviors write facts to the coordinator's belief memory
// (a planned path, detected markers, a saved map's file, an operator's
// answer) and read them. A behavior system started with --coordinator gets
// one in its SystemContext (`context.beliefs`, null without a coordinator).
//
//   if (context.beliefs) {
//     absl::Status s = context.beliefs->writeMessage("drone1/path", path,
//                                                    "drone1/GENERATE_PATH_WITH_OCCUPANCY_GRID");
//   }
//
// Blocking calls with a wall deadline; each failure names the coordinator.
// Thread-safe.

#include <google/protobuf/message.h>
#include <google/protobuf/struct.pb.h>
#include <grpcpp/grpcpp.h>

#include <chrono>
#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"

namespace behaviorlib::server {

class BeliefClient {
 public:
  explicit BeliefClient(std::string coordinator_address,
                        std::chrono::milliseconds timeout = std::chrono::seconds(2));

  const std::string& address() const { return address_; }

  /// Writes `key` (INVALID_ARGUMENT for a bad key, UNAVAILABLE when the
  /// coordinator cannot be reached). `type` names the message type the
  /// value encodes, if any. Returns the stored belief.
  absl::StatusOr<v1::Belief> write(const std::string& key, const google::protobuf::Value& value,
                                   const std::string& writer, const std::string& type = "") const;
  /// Writes a message as its JSON form, with its full type name.
  absl::StatusOr<v1::Belief> writeMessage(const std::string& key,
                                          const google::protobuf::Message& message,
                                          const std::string& writer) const;
  /// NOT_FOUND when absent.
  absl::StatusOr<v1::Belief> read(const std::string& key) const;

 private:
  std::string address_;
  std::chrono::milliseconds timeout_;
  std::unique_ptr<v1::Coordinator::Stub> stub_;
};

}  // namespace behaviorlib::server
