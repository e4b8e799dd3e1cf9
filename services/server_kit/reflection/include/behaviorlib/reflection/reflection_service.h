#pragma once

// gRPC server reflection (grpc.reflection.v1 and grpc.reflection.v1alpha)
// that serves proto descriptors WITH source info, so that
// `grpcurl describe` shows the API documentation. gRPC's built-in reflection
// plugin serves the generated descriptor pool, which has no comments.
//
// Descriptors come from the embedded behaviorlib descriptor set
// (behaviorlib::embedded::descriptorSet()), then from an embedded set of the
// gRPC health and reflection protos, then from the generated pool of the
// process. Do not also link gRPC::grpc++_reflection into the same binary.

// grpc::Service must be complete wherever the returned vector is destroyed;
// this is the light public header that defines it (no protobuf, no generated
// reflection code).
#include <grpcpp/impl/service_type.h>

#include <memory>
#include <string>
#include <vector>

namespace behaviorlib {

inline constexpr char kReflectionV1ServiceName[] = "grpc.reflection.v1.ServerReflection";
inline constexpr char kReflectionV1AlphaServiceName[] = "grpc.reflection.v1alpha.ServerReflection";

/// Returns the grpc.reflection.v1alpha and grpc.reflection.v1 reflection
/// services (callback API; no thread is held per stream). Register every one
/// on the ServerBuilder before BuildAndStart and keep them alive until the
/// server has shut down.
///
/// `service_names` are the fully-qualified names of the services the server
/// serves (e.g. "behaviorlib.v1.BehaviorSystem", "grpc.health.v1.Health");
/// they are what list_services reports. The two reflection services are added
/// when missing; duplicates are dropped.
std::vector<std::unique_ptr<grpc::Service>> makeReflectionServices(
    std::vector<std::string> service_names);

}  // namespace behaviorlib
