#pragma once

#include <google/protobuf/descriptor.h>

namespace behaviorlib::embedded {

/// A pool of every message type of embedded::descriptorSet() (every
/// behaviorlib proto and its imports), built once. Unlike the generated
/// pool, it holds the types a statically linked program does not reference:
/// what a channel sample's Any or a recording may carry.
const google::protobuf::DescriptorPool& descriptorPool();

}  // namespace behaviorlib::embedded
