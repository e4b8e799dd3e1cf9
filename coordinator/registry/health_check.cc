#include "coordinator/registry/health_check.h"

#include <grpcpp/generic/generic_stub.h>

#include <future>
#include <vector>

#include "behaviorlib/server_kit/reactor_order.h"

namespace behaviorlib::coordinator {

namespace {

// grpc.health.v1.HealthCheckResponse.ServingStatus
constexpr int kServing = 1;

const char* statusName(int status) {
  switch (status) {
    case 0:
      return "UNKNOWN";
    case 1:
      return "SERVING";
    case 2:
      return "NOT_SERVING";
    case 3:
      return "SERVICE_UNKNOWN";
    default:
      return "unrecognized";
  }
}

}  // namespace

HealthResult checkHealth(const std::shared_ptr<grpc::Channel>& channel, const std::string& service,
                         std::chrono::milliseconds timeout,
                         const std::function<void(grpc::ClientContext*)>& context_hook) {
  // HealthCheckRequest { string service = 1; }
  std::string request;
  if (!service.empty() && service.size() < 128) {
    request.push_back(0x0a);
    request.push_back(static_cast<char>(service.size()));
    request += service;
  }
  grpc::Slice slice(request);
  grpc::ByteBuffer request_buffer(&slice, 1);
  grpc::ByteBuffer response_buffer;
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + timeout);
  if (context_hook) context_hook(&context);
  grpc::GenericStub stub(channel);
  std::promise<grpc::Status> done;
  stub.UnaryCall(&context, "/grpc.health.v1.Health/Check", grpc::StubOptions(), &request_buffer,
                 &response_buffer, server_kit::orderedCallback([&done](grpc::Status s) {
                   done.set_value(std::move(s));
                 }));
  // The deadline ends the call; wait for the callback in any case, since it
  // refers to this frame.
  const grpc::Status status = done.get_future().get();
  if (context_hook) context_hook(nullptr);

  HealthResult result;
  if (!status.ok()) {
    result.detail = "health check failed: " + status.error_message() + " (code " +
                    std::to_string(static_cast<int>(status.error_code())) + ")";
    return result;
  }
  std::vector<grpc::Slice> slices;
  std::string bytes;
  if (response_buffer.Dump(&slices).ok()) {
    for (const auto& s : slices) bytes.append(reinterpret_cast<const char*>(s.begin()), s.size());
  }
  // HealthCheckResponse { ServingStatus status = 1; }: tag 0x08 and a
  // one-byte varint, or nothing for UNKNOWN (0).
  int serving_status = 0;
  if (bytes.size() == 2 && bytes[0] == 0x08) serving_status = static_cast<unsigned char>(bytes[1]);
  result.serving = serving_status == kServing;
  if (!result.serving) {
    result.detail = std::string("health check answered ") + statusName(serving_status);
  }
  return result;
}

}  // namespace behaviorlib::coordinator
