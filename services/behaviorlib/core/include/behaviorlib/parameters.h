#pragma once

// Parameter messages: validation against the (behaviorlib.v1.param) field
// options, defaults, conversion from/to google.protobuf.Struct (the generic
// BehaviorSystem API and events), and schemas for ListBehaviors. Everything
// is derived from the message descriptor, so a behavior's parameters are
// written once, in its .proto file.
//
//   v1::WaitParameters p;
//   absl::Status s = behaviorlib::params::fromStruct(request.parameters(), &p);
//   if (s.ok()) s = behaviorlib::params::applyDefaultsAndValidate(&p);

#include <google/protobuf/message.h>
#include <google/protobuf/repeated_ptr_field.h>
#include <google/protobuf/struct.pb.h>

#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "behaviorlib/v1/behavior.pb.h"

namespace behaviorlib::params {

/// Fills `out` (cleared first) from a Struct whose keys are field names of
/// out's type. INVALID_ARGUMENT, naming the parameter by its path (e.g.
/// "parameter 'path.poses[2].position_m.x'"), for an unknown field, a wrong
/// JSON type, a non-integral or out-of-type-range number for an integer field,
/// an unknown enum value, or a null. Keys may also be the fields' JSON
/// (lowerCamel) names; enums are accepted by name or number, bytes as base64,
/// map fields as JSON objects.
absl::Status fromStruct(const google::protobuf::Struct& in, google::protobuf::Message* out);

/// The message as a Struct: every field that is set (explicit presence) or
/// non-default (implicit presence); enums as names, 64-bit integers as
/// numbers, bytes as base64 strings, nested messages as objects.
google::protobuf::Struct toStruct(const google::protobuf::Message& message);

/// Sets each unset field that declares a default_json to that default, then
/// checks every rule: required fields set (INVALID_ARGUMENT "parameter 'x' is
/// required: <description>"), numeric values within range (INVALID_ARGUMENT
/// "parameter 'x' = 5 is out of range [0, 3]"), recursively into nested
/// messages, and NaN rejected for floating fields. Without explicit presence
/// a zero/empty value counts as unset (defaults apply, `required` fails), so
/// such fields should be `optional` in the .proto when zero is meaningful. A
/// default_json that does not fit its field is INTERNAL (a schema bug).
absl::Status applyDefaultsAndValidate(google::protobuf::Message* message);

/// Applies a partial update: every field set in `update` (present for
/// explicit-presence fields, non-empty for repeated, non-default otherwise)
/// replaces the same field of `current`; repeated fields are replaced, not
/// appended; nested messages are merged recursively. Same type required.
void mergeUpdate(const google::protobuf::Message& update, google::protobuf::Message* current);

/// One schema entry per field of `descriptor` (recursing into nested
/// messages, guarding against recursive types).
void describe(const google::protobuf::Descriptor& descriptor,
              google::protobuf::RepeatedPtrField<v1::ParameterSchema>* out);

/// A number as the parameter errors print it: the shortest text that reads
/// back to the same double ("0.2", "30", "1e-06").
std::string numberText(double value);
/// A range as the parameter errors print it: "[0.2, 30]", "(-inf, 3]".
std::string rangeText(const v1::Range& range);

/// The unit carried by a field name's suffix ("duration_s" -> "s",
/// "speed_m_s" -> "m/s", "yaw_rad" -> "rad", "accel_m_s2" -> "m/s^2",
/// "rate_hz" -> "Hz"), or "" if none is recognised.
std::string unitOfFieldName(std::string_view name);

}  // namespace behaviorlib::params
