#pragma once

// Belief-memory helpers of the operator_interaction behaviors: key checks
// (the coordinator's rule: letters, digits, '_', '-', '.', segments
// separated by '/') and values.

#include <google/protobuf/struct.pb.h>

#include <string>

#include "behaviorlib/clock.h"

namespace behaviorlib::operator_interaction {

/// A non-empty key segment of letters, digits, '_', '-', '.'.
bool validKeySegment(const std::string& segment);
/// Non-empty '/'-separated valid segments.
bool validKey(const std::string& key);

google::protobuf::Value stringValue(const std::string& s);
google::protobuf::Value numberValue(double d);
/// A time of the behavior clock as RFC 3339 text.
std::string timeText(TimePoint t);

}  // namespace behaviorlib::operator_interaction
