#pragma once

// Whether a JSON value has the type a behavior parameter's schema asks for,
// for the checks of catalog defaults and mission-file literals against the
// schemas the systems registered.

#include <google/protobuf/struct.pb.h>

#include "behaviorlib/v1/behavior.pb.h"

namespace behaviorlib::coordinator {

/// The schema's value type: value_type, or, from a system that predates it,
/// the same read from the text `type`.
inline v1::ParameterType valueTypeOf(const v1::ParameterSchema& schema) {
  if (schema.value_type() != v1::PARAMETER_TYPE_UNSPECIFIED) return schema.value_type();
  const std::string& type = schema.type();
  if (type == "number") return v1::PARAMETER_TYPE_NUMBER;
  if (type == "integer") return v1::PARAMETER_TYPE_INTEGER;
  if (type == "boolean") return v1::PARAMETER_TYPE_BOOLEAN;
  if (type == "string") return v1::PARAMETER_TYPE_STRING;
  if (type == "enum") return v1::PARAMETER_TYPE_ENUM;
  if (type == "object") return v1::PARAMETER_TYPE_OBJECT;
  if (type == "bytes") return v1::PARAMETER_TYPE_BYTES;
  return v1::PARAMETER_TYPE_UNSPECIFIED;
}

/// Whether one value (not a list: the caller checks each element of a
/// repeated parameter) has the schema's JSON type; true for a type unknown.
inline bool valueHasType(const v1::ParameterSchema& schema, const google::protobuf::Value& value) {
  switch (valueTypeOf(schema)) {
    case v1::PARAMETER_TYPE_NUMBER:
    case v1::PARAMETER_TYPE_INTEGER:
      return value.has_number_value();
    case v1::PARAMETER_TYPE_BOOLEAN:
      return value.has_bool_value();
    case v1::PARAMETER_TYPE_STRING:
    case v1::PARAMETER_TYPE_ENUM:
    case v1::PARAMETER_TYPE_BYTES:
      return value.has_string_value();
    case v1::PARAMETER_TYPE_OBJECT:
      return value.has_struct_value();
    default:
      return true;
  }
}

}  // namespace behaviorlib::coordinator
