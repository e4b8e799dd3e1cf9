#include "behaviorlib/server/belief_client.h"

#include <google/protobuf/util/json_util.h>

#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/transport_security.h"

namespace behaviorlib::server {

namespace {

// The coordinator's error, reworded, with its details (reason, metadata).
absl::Status fromGrpc(const grpc::Status& status, const std::string& address,
                      const std::string& what) {
  return errors::rewrap(errors::fromGrpc(status),
                        what + " at the coordinator " + address + ": " + status.error_message());
}

}  // namespace

BeliefClient::BeliefClient(std::string coordinator_address, std::chrono::milliseconds timeout)
    : address_(std::move(coordinator_address)),
      timeout_(timeout),
      stub_(v1::Coordinator::NewStub(behaviorlib::server_kit::makeChannel(address_))) {}

absl::StatusOr<v1::Belief> BeliefClient::write(const std::string& key,
                                               const google::protobuf::Value& value,
                                               const std::string& writer,
                                               const std::string& type) const {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + timeout_);
  v1::WriteBeliefRequest request;
  request.set_key(key);
  *request.mutable_value() = value;
  request.set_writer(writer);
  request.set_type(type);
  v1::WriteBeliefResponse response;
  grpc::Status status = stub_->WriteBelief(&context, request, &response);
  if (!status.ok()) return fromGrpc(status, address_, "writing belief '" + key + "'");
  return response.belief();
}

absl::StatusOr<v1::Belief> BeliefClient::writeMessage(const std::string& key,
                                                      const google::protobuf::Message& message,
                                                      const std::string& writer) const {
  std::string json;
  google::protobuf::util::JsonPrintOptions print;
  print.preserve_proto_field_names = true;
  if (auto s = google::protobuf::util::MessageToJsonString(message, &json, print); !s.ok()) {
    return absl::InternalError("cannot encode " + message.GetTypeName() +
                               " as JSON: " + std::string(s.message()));
  }
  google::protobuf::Value value;
  if (auto s = google::protobuf::util::JsonStringToMessage(json, &value); !s.ok()) {
    return absl::InternalError("cannot decode the JSON of " + message.GetTypeName() + ": " +
                               std::string(s.message()));
  }
  return write(key, value, writer, message.GetTypeName());
}

absl::StatusOr<v1::Belief> BeliefClient::read(const std::string& key) const {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + timeout_);
  v1::ReadBeliefRequest request;
  request.set_key(key);
  v1::ReadBeliefResponse response;
  grpc::Status status = stub_->ReadBelief(&context, request, &response);
  if (!status.ok()) return fromGrpc(status, address_, "reading belief '" + key + "'");
  return response.belief();
}

}  // namespace behaviorlib::server
