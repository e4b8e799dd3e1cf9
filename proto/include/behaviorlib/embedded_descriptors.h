#pragma once

#include <string_view>

namespace behaviorlib::embedded {

/// The serialized google.protobuf.FileDescriptorSet of every behaviorlib proto
/// file and its imports, with source info (comments). Server reflection serves
/// these so that `grpcurl describe` shows the API documentation.
std::string_view descriptorSet();

}  // namespace behaviorlib::embedded
