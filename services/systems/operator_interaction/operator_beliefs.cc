#include "behaviorlib/operator_interaction/operator_beliefs.h"

#include <google/protobuf/util/time_util.h>

#include <algorithm>
#include <sstream>

namespace behaviorlib::operator_interaction {

bool validKeySegment(const std::string& segment) {
  return !segment.empty() && std::all_of(segment.begin(), segment.end(), [](char c) {
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' ||
           c == '-' || c == '.';
  });
}

bool validKey(const std::string& key) {
  if (key.empty()) return false;
  std::istringstream in(key);
  size_t segments = 0;
  for (std::string segment; std::getline(in, segment, '/'); ++segments) {
    if (!validKeySegment(segment)) return false;
  }
  return key.back() != '/' && segments > 0;
}

google::protobuf::Value stringValue(const std::string& s) {
  google::protobuf::Value v;
  v.set_string_value(s);
  return v;
}

google::protobuf::Value numberValue(double d) {
  google::protobuf::Value v;
  v.set_number_value(d);
  return v;
}

std::string timeText(TimePoint t) {
  return google::protobuf::util::TimeUtil::ToString(
      google::protobuf::util::TimeUtil::NanosecondsToTimestamp(t.time_since_epoch().count()));
}

}  // namespace behaviorlib::operator_interaction
