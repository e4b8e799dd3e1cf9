#pragma once

// The proto comments of the behaviorlib API at run time, from the descriptor
// set embedded with source info (behaviorlib::proto_descriptors). ListBehaviors and
// parameter validation use them so that a behavior's description and its parameters' descriptions
// are written once, as comments in its .proto file.

#include <string>

namespace behaviorlib {

/// The leading comment of a service, message, field or enum by full name
/// ("behaviorlib.v1.Wait", "behaviorlib.v1.WaitParameters.duration_s"),
/// whitespace-trimmed and joined into one paragraph; "" when unknown.
std::string leadingComment(const std::string& full_name);

}  // namespace behaviorlib
