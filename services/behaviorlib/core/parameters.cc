#include "behaviorlib/parameters.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/stubs/logging.h>
#include <google/protobuf/util/json_util.h>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <limits>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/escaping.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "behaviorlib/documentation.h"
#include "behaviorlib/errors/status_details.h"
#include "behaviorlib/v1/options.pb.h"

namespace behaviorlib::params {
namespace {

namespace pb = google::protobuf;
using FD = pb::FieldDescriptor;

// describe() output is for humans and tools; past this depth a schema is
// unreadable anyway, and the limit bounds the output for deep non-recursive
// type chains that the on-path guard does not catch.
constexpr int kMaxDescribeDepth = 8;

// Long string values are cut in error messages so that one bad parameter
// cannot blow up a log line or a gRPC status.
constexpr size_t kMaxQuotedLength = 60;

const v1::ParameterRule& ruleOf(const FD& field) { return field.options().GetExtension(v1::param); }

// The rule's description, else the field's comment in its .proto file.
std::string descriptionOf(const FD& field, const v1::ParameterRule& rule) {
  return rule.description().empty() ? leadingComment(field.full_name()) : rule.description();
}

// Shortest text that reads back as the same double, so that error messages
// show exactly what the caller sent ("2.5", "86400", "1e+40").
std::string formatNumber(double v) {
  if (std::isnan(v)) return "NaN";
  if (std::isinf(v)) return v > 0 ? "Infinity" : "-Infinity";
  char buf[64];
  // Integral values print like integers ("3000000000", not "3e+09"), as
  // JavaScript does below 1e21, so they read as what the caller typed.
  const auto result = std::trunc(v) == v && std::abs(v) < 1e21
                          ? std::to_chars(buf, buf + sizeof(buf), v, std::chars_format::fixed)
                          : std::to_chars(buf, buf + sizeof(buf), v);
  return std::string(buf, result.ptr);
}

// A float converted through its shortest decimal text: 0.1f becomes 0.1, not
// 0.10000000149011612, which is what the caller wrote and expects back.
double floatToDouble(float v) {
  if (!std::isfinite(v)) return static_cast<double>(v);
  char buf[32];
  const auto written = std::to_chars(buf, buf + sizeof(buf), v);
  double d = 0;
  std::from_chars(buf, written.ptr, d);
  return d;
}

// The float's shortest text: 0.1f prints as "0.1".
std::string formatFloat(float v) { return formatNumber(floatToDouble(v)); }

std::string quoted(absl::string_view s) {
  if (s.size() > kMaxQuotedLength) {
    return absl::StrCat("\"", absl::CHexEscape(s.substr(0, kMaxQuotedLength)), "\"...");
  }
  return absl::StrCat("\"", absl::CHexEscape(s), "\"");
}

// "a string ("five")": what the caller actually sent, for "got ..." messages.
std::string describeValue(const pb::Value& v) {
  switch (v.kind_case()) {
    case pb::Value::kNullValue:
      return "null";
    case pb::Value::kNumberValue:
      return absl::StrCat("a number (", formatNumber(v.number_value()), ")");
    case pb::Value::kStringValue:
      return absl::StrCat("a string (", quoted(v.string_value()), ")");
    case pb::Value::kBoolValue:
      return absl::StrCat("a boolean (", v.bool_value() ? "true" : "false", ")");
    case pb::Value::kStructValue:
      return "an object";
    case pb::Value::kListValue:
      return "a list";
    case pb::Value::KIND_NOT_SET:
      break;
  }
  return "no value";
}

std::string childPath(const std::string& parent, absl::string_view name) {
  return parent.empty() ? std::string(name) : absl::StrCat(parent, ".", name);
}

std::string elementPath(const std::string& parent, int index) {
  return absl::StrCat(parent, "[", index, "]");
}

// Map keys are shown as they are written in JSON: strings quoted, numbers
// and booleans bare.
std::string mapKeyPath(const std::string& parent, const FD& key_field, absl::string_view key) {
  if (key_field.cpp_type() == FD::CPPTYPE_STRING) {
    return absl::StrCat(parent, "[", quoted(key), "]");
  }
  return absl::StrCat(parent, "[", key, "]");
}

// INVALID_ARGUMENT with a machine-readable reason and the parameter's path as
// a BadRequest field violation (errors.proto).
absl::Status fieldError(const std::string& path, std::string message,
                        v1::ErrorReason reason = v1::PARAMETER_INVALID) {
  absl::Status status = absl::InvalidArgumentError(message);
  status = errors::withFieldViolation(std::move(status), path, message);
  return errors::withReason(std::move(status), reason);
}

absl::Status paramError(const std::string& path, absl::string_view what,
                        v1::ErrorReason reason = v1::PARAMETER_INVALID) {
  return fieldError(path, absl::StrCat("parameter '", path, "': ", what), reason);
}

std::string enumNames(const pb::EnumDescriptor& e) {
  std::vector<std::string> names;
  names.reserve(e.value_count());
  for (int i = 0; i < e.value_count(); ++i) names.push_back(e.value(i)->name());
  return absl::StrJoin(names, ", ");
}

// What a field (or one element of a repeated field) accepts, for "expected
// ..." messages.
std::string expectedKind(const FD& field) {
  switch (field.cpp_type()) {
    case FD::CPPTYPE_INT32:
    case FD::CPPTYPE_INT64:
    case FD::CPPTYPE_UINT32:
    case FD::CPPTYPE_UINT64:
      return "an integer";
    case FD::CPPTYPE_DOUBLE:
    case FD::CPPTYPE_FLOAT:
      return "a number";
    case FD::CPPTYPE_BOOL:
      return "a boolean";
    case FD::CPPTYPE_STRING:
      return field.type() == FD::TYPE_BYTES ? "a base64 string" : "a string";
    case FD::CPPTYPE_ENUM:
      return absl::StrCat("one of ", enumNames(*field.enum_type()));
    case FD::CPPTYPE_MESSAGE:
      return "an object";
  }
  return "a value";
}

absl::Status expectedError(const std::string& path, absl::string_view expected,
                           const pb::Value& got) {
  return paramError(path, absl::StrCat("expected ", expected, ", got ", describeValue(got)));
}

// Checks that a JSON number is an integer that fits the field's C++ type. The
// bounds are compared as doubles: 2^63 and 2^64 are exact in a double, and
// the largest doubles below them are in range.
absl::Status checkInteger(double d, const FD& field, const std::string& path) {
  if (!std::isfinite(d) || std::trunc(d) != d) {
    return paramError(path, absl::StrCat(formatNumber(d), " is not an integer"));
  }
  const bool is_unsigned =
      field.cpp_type() == FD::CPPTYPE_UINT32 || field.cpp_type() == FD::CPPTYPE_UINT64;
  if (is_unsigned && d < 0) {
    return paramError(path, absl::StrCat(formatNumber(d), " is negative, but the parameter is ",
                                         field.type_name(), " (unsigned)"));
  }
  double lo = 0;
  double hi = 0;
  std::string bounds;
  switch (field.cpp_type()) {
    case FD::CPPTYPE_INT32:
      lo = std::numeric_limits<int32_t>::min();
      hi = std::numeric_limits<int32_t>::max();
      bounds = absl::StrCat("[", std::numeric_limits<int32_t>::min(), ", ",
                            std::numeric_limits<int32_t>::max(), "]");
      break;
    case FD::CPPTYPE_UINT32:
      hi = std::numeric_limits<uint32_t>::max();
      bounds = absl::StrCat("[0, ", std::numeric_limits<uint32_t>::max(), "]");
      break;
    case FD::CPPTYPE_INT64:
      lo = -0x1p63;
      hi = std::nextafter(0x1p63, 0.0);
      bounds = absl::StrCat("[", std::numeric_limits<int64_t>::min(), ", ",
                            std::numeric_limits<int64_t>::max(), "]");
      break;
    case FD::CPPTYPE_UINT64:
      hi = std::nextafter(0x1p64, 0.0);
      bounds = absl::StrCat("[0, ", std::numeric_limits<uint64_t>::max(), "]");
      break;
    default:
      return absl::OkStatus();
  }
  if (d < lo || d > hi) {
    return paramError(
        path,
        absl::StrCat(formatNumber(d), " is out of range for ", field.type_name(), " ", bounds),
        v1::PARAMETER_OUT_OF_RANGE);
  }
  return absl::OkStatus();
}

// Where one converted value goes: the singular field, a new element of a
// repeated field, or the value of a map entry. Lets singular, repeated and
// map fields share one conversion.
struct Slot {
  pb::Message* message;
  const FD* field;
  bool add;

  const pb::Reflection* reflection() const { return message->GetReflection(); }
  void setInt32(int32_t v) const {
    add ? reflection()->AddInt32(message, field, v) : reflection()->SetInt32(message, field, v);
  }
  void setInt64(int64_t v) const {
    add ? reflection()->AddInt64(message, field, v) : reflection()->SetInt64(message, field, v);
  }
  void setUInt32(uint32_t v) const {
    add ? reflection()->AddUInt32(message, field, v) : reflection()->SetUInt32(message, field, v);
  }
  void setUInt64(uint64_t v) const {
    add ? reflection()->AddUInt64(message, field, v) : reflection()->SetUInt64(message, field, v);
  }
  void setDouble(double v) const {
    add ? reflection()->AddDouble(message, field, v) : reflection()->SetDouble(message, field, v);
  }
  void setFloat(float v) const {
    add ? reflection()->AddFloat(message, field, v) : reflection()->SetFloat(message, field, v);
  }
  void setBool(bool v) const {
    add ? reflection()->AddBool(message, field, v) : reflection()->SetBool(message, field, v);
  }
  void setString(std::string v) const {
    add ? reflection()->AddString(message, field, std::move(v))
        : reflection()->SetString(message, field, std::move(v));
  }
  void setEnum(int v) const {
    add ? reflection()->AddEnumValue(message, field, v)
        : reflection()->SetEnumValue(message, field, v);
  }
  pb::Message* mutableMessage() const {
    return add ? reflection()->AddMessage(message, field)
               : reflection()->MutableMessage(message, field);
  }
};

absl::Status parseMessage(const pb::Struct& in, pb::Message* out, const std::string& path);

// Converts one JSON value (not a list: a single value or list element) into
// the slot's field type.
absl::Status parseSingle(const pb::Value& v, const Slot& slot, const std::string& path) {
  const FD& field = *slot.field;
  switch (field.cpp_type()) {
    case FD::CPPTYPE_INT32:
    case FD::CPPTYPE_INT64:
    case FD::CPPTYPE_UINT32:
    case FD::CPPTYPE_UINT64: {
      if (v.kind_case() != pb::Value::kNumberValue) {
        return expectedError(path, expectedKind(field), v);
      }
      const double d = v.number_value();
      if (absl::Status s = checkInteger(d, field, path); !s.ok()) return s;
      switch (field.cpp_type()) {
        case FD::CPPTYPE_INT32:
          slot.setInt32(static_cast<int32_t>(d));
          break;
        case FD::CPPTYPE_INT64:
          slot.setInt64(static_cast<int64_t>(d));
          break;
        case FD::CPPTYPE_UINT32:
          slot.setUInt32(static_cast<uint32_t>(d));
          break;
        default:
          slot.setUInt64(static_cast<uint64_t>(d));
          break;
      }
      return absl::OkStatus();
    }
    case FD::CPPTYPE_DOUBLE:
    case FD::CPPTYPE_FLOAT: {
      if (v.kind_case() != pb::Value::kNumberValue) {
        return expectedError(path, expectedKind(field), v);
      }
      const double d = v.number_value();
      // JSON cannot carry NaN or infinities; a Struct built in code can, and
      // no behavior can act on one.
      if (!std::isfinite(d)) {
        return paramError(path, absl::StrCat(formatNumber(d), " is not a finite number"));
      }
      if (field.cpp_type() == FD::CPPTYPE_DOUBLE) {
        slot.setDouble(d);
        return absl::OkStatus();
      }
      if (std::abs(d) > std::numeric_limits<float>::max()) {
        return paramError(path, absl::StrCat(formatNumber(d), " is out of range for float"));
      }
      slot.setFloat(static_cast<float>(d));
      return absl::OkStatus();
    }
    case FD::CPPTYPE_BOOL:
      if (v.kind_case() != pb::Value::kBoolValue) {
        return expectedError(path, expectedKind(field), v);
      }
      slot.setBool(v.bool_value());
      return absl::OkStatus();
    case FD::CPPTYPE_STRING: {
      if (v.kind_case() != pb::Value::kStringValue) {
        return expectedError(path, expectedKind(field), v);
      }
      if (field.type() != FD::TYPE_BYTES) {
        slot.setString(v.string_value());
        return absl::OkStatus();
      }
      // Proto3 JSON writes bytes as standard base64 but accepts the URL-safe
      // alphabet too; so do we.
      std::string decoded;
      if (!absl::Base64Unescape(v.string_value(), &decoded) &&
          !absl::WebSafeBase64Unescape(v.string_value(), &decoded)) {
        return paramError(path, absl::StrCat(quoted(v.string_value()), " is not valid base64"));
      }
      slot.setString(std::move(decoded));
      return absl::OkStatus();
    }
    case FD::CPPTYPE_ENUM: {
      const pb::EnumDescriptor& e = *field.enum_type();
      if (v.kind_case() == pb::Value::kStringValue) {
        const pb::EnumValueDescriptor* value = e.FindValueByName(v.string_value());
        if (value == nullptr) {
          return paramError(path, absl::StrCat("unknown value ", quoted(v.string_value()),
                                               "; accepted: ", enumNames(e)));
        }
        slot.setEnum(value->number());
        return absl::OkStatus();
      }
      if (v.kind_case() == pb::Value::kNumberValue) {
        const double d = v.number_value();
        if (!std::isfinite(d) || std::trunc(d) != d) {
          return paramError(path, absl::StrCat(formatNumber(d), " is not an integer"));
        }
        const pb::EnumValueDescriptor* value =
            (d >= std::numeric_limits<int32_t>::min() && d <= std::numeric_limits<int32_t>::max())
                ? e.FindValueByNumber(static_cast<int>(d))
                : nullptr;
        if (value == nullptr) {
          // Numbers are the less common spelling, so show the mapping.
          std::vector<std::string> accepted;
          for (int i = 0; i < e.value_count(); ++i) {
            accepted.push_back(absl::StrCat(e.value(i)->name(), " (", e.value(i)->number(), ")"));
          }
          return paramError(path, absl::StrCat("unknown value ", formatNumber(d),
                                               "; accepted: ", absl::StrJoin(accepted, ", ")));
        }
        slot.setEnum(value->number());
        return absl::OkStatus();
      }
      return expectedError(path, expectedKind(field), v);
    }
    case FD::CPPTYPE_MESSAGE:
      if (v.kind_case() != pb::Value::kStructValue) {
        return expectedError(path, expectedKind(field), v);
      }
      return parseMessage(v.struct_value(), slot.mutableMessage(), path);
  }
  return paramError(path, "unsupported field type");
}

// Sets an entry's key field from a JSON object key (always a string).
absl::Status parseMapKey(const std::string& key, pb::Message* entry, const FD& key_field,
                         const std::string& path) {
  const pb::Reflection* r = entry->GetReflection();
  bool ok = true;
  switch (key_field.cpp_type()) {
    case FD::CPPTYPE_STRING:
      r->SetString(entry, &key_field, key);
      break;
    case FD::CPPTYPE_INT32: {
      int32_t v = 0;
      ok = absl::SimpleAtoi(key, &v);
      if (ok) r->SetInt32(entry, &key_field, v);
      break;
    }
    case FD::CPPTYPE_INT64: {
      int64_t v = 0;
      ok = absl::SimpleAtoi(key, &v);
      if (ok) r->SetInt64(entry, &key_field, v);
      break;
    }
    case FD::CPPTYPE_UINT32: {
      uint32_t v = 0;
      ok = absl::SimpleAtoi(key, &v);
      if (ok) r->SetUInt32(entry, &key_field, v);
      break;
    }
    case FD::CPPTYPE_UINT64: {
      uint64_t v = 0;
      ok = absl::SimpleAtoi(key, &v);
      if (ok) r->SetUInt64(entry, &key_field, v);
      break;
    }
    case FD::CPPTYPE_BOOL:
      ok = key == "true" || key == "false";
      if (ok) r->SetBool(entry, &key_field, key == "true");
      break;
    default:
      ok = false;
      break;
  }
  if (!ok) {
    return paramError(path,
                      absl::StrCat("key ", quoted(key), " is not a valid ", key_field.type_name()));
  }
  return absl::OkStatus();
}

template <typename Map>
std::vector<const typename Map::value_type*> sortedEntries(const Map& map) {
  // Struct fields are a hash map; sorting makes the first reported error (and
  // map insertion order) independent of hashing.
  std::vector<const typename Map::value_type*> entries;
  entries.reserve(map.size());
  for (const auto& entry : map) entries.push_back(&entry);
  std::sort(entries.begin(), entries.end(),
            [](const auto* a, const auto* b) { return a->first < b->first; });
  return entries;
}

// Converts the JSON value of one field (a list for repeated fields, an object
// for maps) into `out`.
absl::Status parseField(const pb::Value& v, const FD& field, pb::Message* out,
                        const std::string& path) {
  if (v.kind_case() == pb::Value::kNullValue) {
    return paramError(path, "null is not accepted; omit the parameter to leave it unset");
  }
  if (field.is_map()) {
    if (v.kind_case() != pb::Value::kStructValue) {
      return expectedError(path, "an object", v);
    }
    const FD& key_field = *field.message_type()->map_key();
    const FD& value_field = *field.message_type()->map_value();
    for (const auto* item : sortedEntries(v.struct_value().fields())) {
      const std::string item_path = mapKeyPath(path, key_field, item->first);
      pb::Message* entry = out->GetReflection()->AddMessage(out, &field);
      if (absl::Status s = parseMapKey(item->first, entry, key_field, path); !s.ok()) return s;
      if (absl::Status s = parseSingle(item->second, Slot{entry, &value_field, false}, item_path);
          !s.ok()) {
        return s;
      }
    }
    return absl::OkStatus();
  }
  if (field.is_repeated()) {
    if (v.kind_case() != pb::Value::kListValue) {
      return expectedError(path, "a list", v);
    }
    const auto& values = v.list_value().values();
    for (int i = 0; i < values.size(); ++i) {
      if (absl::Status s = parseSingle(values[i], Slot{out, &field, true}, elementPath(path, i));
          !s.ok()) {
        return s;
      }
    }
    return absl::OkStatus();
  }
  return parseSingle(v, Slot{out, &field, false}, path);
}

// Field names as written in the .proto file are canonical; the JSON names
// ("durationS") are accepted because proto3 JSON tools produce them.
const FD* findField(const pb::Descriptor& d, const std::string& key) {
  if (const FD* f = d.FindFieldByName(key)) return f;
  for (int i = 0; i < d.field_count(); ++i) {
    const FD* f = d.field(i);
    if (f->json_name() == key || f->camelcase_name() == key) return f;
  }
  return nullptr;
}

absl::Status parseMessage(const pb::Struct& in, pb::Message* out, const std::string& path) {
  const pb::Descriptor& d = *out->GetDescriptor();
  // Key each field was given under, to report a field given twice under its
  // two spellings, or two members of one oneof.
  std::vector<std::pair<const FD*, const std::string*>> given;
  for (const auto* item : sortedEntries(in.fields())) {
    const FD* field = findField(d, item->first);
    if (field == nullptr) {
      std::vector<std::string> known;
      for (int i = 0; i < d.field_count(); ++i) known.push_back(d.field(i)->name());
      return fieldError(childPath(path, item->first),
                        absl::StrCat("unknown parameter '", childPath(path, item->first), "' for ",
                                     d.full_name(), "; known parameters: ",
                                     known.empty() ? "(none)" : absl::StrJoin(known, ", ")));
    }
    for (const auto& [other, other_key] : given) {
      if (other == field) {
        return fieldError(
            childPath(path, field->name()),
            absl::StrCat("parameter '", childPath(path, field->name()), "' is given twice, as '",
                         *other_key, "' and as '", item->first, "'"));
      }
      const pb::OneofDescriptor* oneof = field->real_containing_oneof();
      if (oneof != nullptr && other->real_containing_oneof() == oneof) {
        return fieldError(childPath(path, field->name()),
                          absl::StrCat("parameters '", childPath(path, other->name()), "' and '",
                                       childPath(path, field->name()), "' are alternatives (oneof ",
                                       oneof->name(), "); set only one"));
      }
    }
    given.emplace_back(field, &item->first);
    if (absl::Status s = parseField(item->second, *field, out, childPath(path, field->name()));
        !s.ok()) {
      return s;
    }
  }
  return absl::OkStatus();
}

// --- toStruct ----------------------------------------------------------------

pb::Struct messageToStruct(const pb::Message& message);

// One value of `field`: the singular value when index < 0, else an element.
pb::Value singleToValue(const pb::Message& m, const FD& field, int index) {
  const pb::Reflection* r = m.GetReflection();
  const bool rep = index >= 0;
  pb::Value out;
  switch (field.cpp_type()) {
    case FD::CPPTYPE_INT32:
      out.set_number_value(rep ? r->GetRepeatedInt32(m, &field, index) : r->GetInt32(m, &field));
      break;
    case FD::CPPTYPE_INT64:
      out.set_number_value(static_cast<double>(rep ? r->GetRepeatedInt64(m, &field, index)
                                                   : r->GetInt64(m, &field)));
      break;
    case FD::CPPTYPE_UINT32:
      out.set_number_value(rep ? r->GetRepeatedUInt32(m, &field, index) : r->GetUInt32(m, &field));
      break;
    case FD::CPPTYPE_UINT64:
      out.set_number_value(static_cast<double>(rep ? r->GetRepeatedUInt64(m, &field, index)
                                                   : r->GetUInt64(m, &field)));
      break;
    case FD::CPPTYPE_DOUBLE:
      out.set_number_value(rep ? r->GetRepeatedDouble(m, &field, index) : r->GetDouble(m, &field));
      break;
    case FD::CPPTYPE_FLOAT:
      out.set_number_value(
          floatToDouble(rep ? r->GetRepeatedFloat(m, &field, index) : r->GetFloat(m, &field)));
      break;
    case FD::CPPTYPE_BOOL:
      out.set_bool_value(rep ? r->GetRepeatedBool(m, &field, index) : r->GetBool(m, &field));
      break;
    case FD::CPPTYPE_STRING: {
      std::string s = rep ? r->GetRepeatedString(m, &field, index) : r->GetString(m, &field);
      out.set_string_value(field.type() == FD::TYPE_BYTES ? absl::Base64Escape(s) : std::move(s));
      break;
    }
    case FD::CPPTYPE_ENUM: {
      const int number =
          rep ? r->GetRepeatedEnumValue(m, &field, index) : r->GetEnumValue(m, &field);
      // An open enum can hold a number without a name; keep it rather than
      // losing it.
      const pb::EnumValueDescriptor* value = field.enum_type()->FindValueByNumber(number);
      if (value != nullptr) {
        out.set_string_value(value->name());
      } else {
        out.set_number_value(number);
      }
      break;
    }
    case FD::CPPTYPE_MESSAGE:
      *out.mutable_struct_value() =
          messageToStruct(rep ? r->GetRepeatedMessage(m, &field, index) : r->GetMessage(m, &field));
      break;
  }
  return out;
}

std::string mapKeyText(const pb::Message& entry, const FD& key_field) {
  const pb::Reflection* r = entry.GetReflection();
  switch (key_field.cpp_type()) {
    case FD::CPPTYPE_INT32:
      return absl::StrCat(r->GetInt32(entry, &key_field));
    case FD::CPPTYPE_INT64:
      return absl::StrCat(r->GetInt64(entry, &key_field));
    case FD::CPPTYPE_UINT32:
      return absl::StrCat(r->GetUInt32(entry, &key_field));
    case FD::CPPTYPE_UINT64:
      return absl::StrCat(r->GetUInt64(entry, &key_field));
    case FD::CPPTYPE_BOOL:
      return r->GetBool(entry, &key_field) ? "true" : "false";
    case FD::CPPTYPE_STRING:
      return r->GetString(entry, &key_field);
    default:
      return "";
  }
}

pb::Struct messageToStruct(const pb::Message& message) {
  const pb::Reflection* r = message.GetReflection();
  std::vector<const FD*> fields;
  // ListFields yields exactly the fields the header promises: present ones
  // with explicit presence, non-default ones otherwise, non-empty repeated.
  r->ListFields(message, &fields);
  pb::Struct out;
  for (const FD* field : fields) {
    pb::Value& value = (*out.mutable_fields())[field->name()];
    if (field->is_map()) {
      const FD& key_field = *field->message_type()->map_key();
      const FD& value_field = *field->message_type()->map_value();
      auto* object = value.mutable_struct_value()->mutable_fields();
      for (int i = 0; i < r->FieldSize(message, field); ++i) {
        const pb::Message& entry = r->GetRepeatedMessage(message, field, i);
        (*object)[mapKeyText(entry, key_field)] = singleToValue(entry, value_field, -1);
      }
    } else if (field->is_repeated()) {
      pb::ListValue* list = value.mutable_list_value();
      for (int i = 0; i < r->FieldSize(message, field); ++i) {
        *list->add_values() = singleToValue(message, *field, i);
      }
    } else {
      value = singleToValue(message, *field, -1);
    }
  }
  return out;
}

// --- applyDefaultsAndValidate --------------------------------------------------

// Whether the caller (or a default) gave the field a value. For implicit
// presence scalars, HasField is "non-zero": the best that can be known.
bool isSet(const pb::Message& m, const FD& field) {
  const pb::Reflection* r = m.GetReflection();
  if (field.is_repeated()) return r->FieldSize(m, &field) > 0;
  return r->HasField(m, &field);
}

// A default_json that does not fit its field is a bug in the behavior's
// .proto, not in the request: INTERNAL, naming the schema.
absl::Status applyDefault(const v1::ParameterRule& rule, const FD& field, pb::Message* m,
                          const std::string& path) {
  pb::Value value;
  const auto parsed = pb::util::JsonStringToMessage(rule.default_json(), &value);
  if (!parsed.ok()) {
    return absl::InternalError(absl::StrCat(
        "schema error in ", field.full_name(), ": default_json ", quoted(rule.default_json()),
        " is not valid JSON: ", std::string(parsed.message().data(), parsed.message().size())));
  }
  if (absl::Status s = parseField(value, field, m, path); !s.ok()) {
    m->GetReflection()->ClearField(m, &field);
    return absl::InternalError(absl::StrCat("schema error in ", field.full_name(),
                                            ": default_json ", quoted(rule.default_json()),
                                            " does not fit the field: ", s.message()));
  }
  return absl::OkStatus();
}

std::string describeRange(const v1::Range& range) {
  return absl::StrCat(
      range.has_min() ? absl::StrCat("[", formatNumber(range.min())) : std::string("(-inf"), ", ",
      range.has_max() ? absl::StrCat(formatNumber(range.max()), "]") : std::string("+inf)"));
}

// A numeric value of a field, with its exact text (64-bit integers beyond
// 2^53 would be misprinted through a double).
struct Numeric {
  double value;
  std::string text;
  bool floating;
};

std::optional<Numeric> numericAt(const pb::Message& m, const FD& field, int index) {
  const pb::Reflection* r = m.GetReflection();
  const bool rep = index >= 0;
  switch (field.cpp_type()) {
    case FD::CPPTYPE_INT32: {
      const int32_t v = rep ? r->GetRepeatedInt32(m, &field, index) : r->GetInt32(m, &field);
      return Numeric{static_cast<double>(v), absl::StrCat(v), false};
    }
    case FD::CPPTYPE_INT64: {
      const int64_t v = rep ? r->GetRepeatedInt64(m, &field, index) : r->GetInt64(m, &field);
      return Numeric{static_cast<double>(v), absl::StrCat(v), false};
    }
    case FD::CPPTYPE_UINT32: {
      const uint32_t v = rep ? r->GetRepeatedUInt32(m, &field, index) : r->GetUInt32(m, &field);
      return Numeric{static_cast<double>(v), absl::StrCat(v), false};
    }
    case FD::CPPTYPE_UINT64: {
      const uint64_t v = rep ? r->GetRepeatedUInt64(m, &field, index) : r->GetUInt64(m, &field);
      return Numeric{static_cast<double>(v), absl::StrCat(v), false};
    }
    case FD::CPPTYPE_DOUBLE: {
      const double v = rep ? r->GetRepeatedDouble(m, &field, index) : r->GetDouble(m, &field);
      return Numeric{v, formatNumber(v), true};
    }
    case FD::CPPTYPE_FLOAT: {
      const float v = rep ? r->GetRepeatedFloat(m, &field, index) : r->GetFloat(m, &field);
      return Numeric{static_cast<double>(v), formatFloat(v), true};
    }
    default:
      return std::nullopt;
  }
}

absl::Status checkNumeric(const pb::Message& m, const FD& field, int index,
                          const v1::ParameterRule& rule, const std::string& path) {
  const std::optional<Numeric> n = numericAt(m, field, index);
  if (!n) return absl::OkStatus();
  if (n->floating && !std::isfinite(n->value)) {
    return fieldError(
        path, absl::StrCat("parameter '", path, "' = ", n->text, " is not a finite number"));
  }
  if (!rule.has_range()) return absl::OkStatus();
  const v1::Range& range = rule.range();
  if ((range.has_min() && n->value < range.min()) || (range.has_max() && n->value > range.max())) {
    return fieldError(path,
                      absl::StrCat("parameter '", path, "' = ", n->text, " is out of range ",
                                   describeRange(range)),
                      v1::PARAMETER_OUT_OF_RANGE);
  }
  return absl::OkStatus();
}

absl::Status validateMessage(pb::Message* m, const std::string& path);

absl::Status validateField(pb::Message* m, const FD& field, const std::string& path) {
  const pb::Reflection* r = m->GetReflection();
  const v1::ParameterRule& rule = ruleOf(field);
  // A default on a oneof member must not displace the member the caller
  // chose.
  const pb::OneofDescriptor* oneof = field.real_containing_oneof();
  const bool oneof_taken = oneof != nullptr && r->HasOneof(*m, oneof);
  if (!rule.default_json().empty() && !isSet(*m, field) && !oneof_taken) {
    if (absl::Status s = applyDefault(rule, field, m, path); !s.ok()) return s;
  }
  if (rule.required() && !isSet(*m, field)) {
    return fieldError(path, descriptionOf(field, rule).empty()
                                ? absl::StrCat("parameter '", path, "' is required")
                                : absl::StrCat("parameter '", path,
                                               "' is required: ", descriptionOf(field, rule)));
  }
  if (field.is_map()) {
    const FD& key_field = *field.message_type()->map_key();
    const FD& value_field = *field.message_type()->map_value();
    for (int i = 0; i < r->FieldSize(*m, &field); ++i) {
      pb::Message* entry = r->MutableRepeatedMessage(m, &field, i);
      const std::string entry_path = mapKeyPath(path, key_field, mapKeyText(*entry, key_field));
      if (value_field.cpp_type() == FD::CPPTYPE_MESSAGE) {
        if (entry->GetReflection()->HasField(*entry, &value_field)) {
          pb::Message* value = entry->GetReflection()->MutableMessage(entry, &value_field);
          if (absl::Status s = validateMessage(value, entry_path); !s.ok()) return s;
        }
      } else if (absl::Status s = checkNumeric(*entry, value_field, -1, rule, entry_path);
                 !s.ok()) {
        return s;
      }
    }
    return absl::OkStatus();
  }
  if (field.is_repeated()) {
    for (int i = 0; i < r->FieldSize(*m, &field); ++i) {
      absl::Status s =
          field.cpp_type() == FD::CPPTYPE_MESSAGE
              ? validateMessage(r->MutableRepeatedMessage(m, &field, i), elementPath(path, i))
              : checkNumeric(*m, field, i, rule, elementPath(path, i));
      if (!s.ok()) return s;
    }
    return absl::OkStatus();
  }
  if (field.cpp_type() == FD::CPPTYPE_MESSAGE) {
    return r->HasField(*m, &field) ? validateMessage(r->MutableMessage(m, &field), path)
                                   : absl::OkStatus();
  }
  // An implicit-presence scalar always has a value the behavior will use, so
  // it is checked even when it is zero.
  if (field.has_presence() && !r->HasField(*m, &field)) return absl::OkStatus();
  return checkNumeric(*m, field, -1, rule, path);
}

absl::Status validateMessage(pb::Message* m, const std::string& path) {
  const pb::Descriptor& d = *m->GetDescriptor();
  for (int i = 0; i < d.field_count(); ++i) {
    const FD& field = *d.field(i);
    if (absl::Status s = validateField(m, field, childPath(path, field.name())); !s.ok()) {
      return s;
    }
  }
  return absl::OkStatus();
}

// --- mergeUpdate -------------------------------------------------------------

// Appends element `index` of `from`'s repeated `field` to `to` (or sets the
// singular value when index < 0).
void copyValue(const pb::Message& from, const FD& field, int index, pb::Message* to) {
  const pb::Reflection* rf = from.GetReflection();
  const Slot slot{to, &field, index >= 0};
  const bool rep = index >= 0;
  switch (field.cpp_type()) {
    case FD::CPPTYPE_INT32:
      slot.setInt32(rep ? rf->GetRepeatedInt32(from, &field, index) : rf->GetInt32(from, &field));
      break;
    case FD::CPPTYPE_INT64:
      slot.setInt64(rep ? rf->GetRepeatedInt64(from, &field, index) : rf->GetInt64(from, &field));
      break;
    case FD::CPPTYPE_UINT32:
      slot.setUInt32(rep ? rf->GetRepeatedUInt32(from, &field, index)
                         : rf->GetUInt32(from, &field));
      break;
    case FD::CPPTYPE_UINT64:
      slot.setUInt64(rep ? rf->GetRepeatedUInt64(from, &field, index)
                         : rf->GetUInt64(from, &field));
      break;
    case FD::CPPTYPE_DOUBLE:
      slot.setDouble(rep ? rf->GetRepeatedDouble(from, &field, index)
                         : rf->GetDouble(from, &field));
      break;
    case FD::CPPTYPE_FLOAT:
      slot.setFloat(rep ? rf->GetRepeatedFloat(from, &field, index) : rf->GetFloat(from, &field));
      break;
    case FD::CPPTYPE_BOOL:
      slot.setBool(rep ? rf->GetRepeatedBool(from, &field, index) : rf->GetBool(from, &field));
      break;
    case FD::CPPTYPE_STRING:
      slot.setString(rep ? rf->GetRepeatedString(from, &field, index)
                         : rf->GetString(from, &field));
      break;
    case FD::CPPTYPE_ENUM:
      slot.setEnum(rep ? rf->GetRepeatedEnumValue(from, &field, index)
                       : rf->GetEnumValue(from, &field));
      break;
    case FD::CPPTYPE_MESSAGE:
      slot.mutableMessage()->CopyFrom(rep ? rf->GetRepeatedMessage(from, &field, index)
                                          : rf->GetMessage(from, &field));
      break;
  }
}

// --- describe ----------------------------------------------------------------

v1::ParameterType valueTypeOf(const FD& field) {
  switch (field.cpp_type()) {
    case FD::CPPTYPE_DOUBLE:
    case FD::CPPTYPE_FLOAT:
      return v1::PARAMETER_TYPE_NUMBER;
    case FD::CPPTYPE_INT32:
    case FD::CPPTYPE_INT64:
    case FD::CPPTYPE_UINT32:
    case FD::CPPTYPE_UINT64:
      return v1::PARAMETER_TYPE_INTEGER;
    case FD::CPPTYPE_BOOL:
      return v1::PARAMETER_TYPE_BOOLEAN;
    case FD::CPPTYPE_STRING:
      return field.type() == FD::TYPE_BYTES ? v1::PARAMETER_TYPE_BYTES : v1::PARAMETER_TYPE_STRING;
    case FD::CPPTYPE_ENUM:
      return v1::PARAMETER_TYPE_ENUM;
    case FD::CPPTYPE_MESSAGE:
      return v1::PARAMETER_TYPE_OBJECT;
  }
  return v1::PARAMETER_TYPE_UNSPECIFIED;
}

// ParameterSchema.type, the text form of its value_type: "number", ...
void setValueType(v1::ParameterType type, v1::ParameterSchema* schema) {
  schema->set_value_type(type);
  std::string name = v1::ParameterType_Name(type);
  constexpr std::string_view kPrefix = "PARAMETER_TYPE_";
  name = type == v1::PARAMETER_TYPE_UNSPECIFIED
             ? ""
             : absl::AsciiStrToLower(name.substr(kPrefix.size()));
  schema->set_type(std::move(name));
}

std::string protoTypeOf(const FD& field) {
  switch (field.type()) {
    case FD::TYPE_ENUM:
      return field.enum_type()->full_name();
    case FD::TYPE_MESSAGE:
    case FD::TYPE_GROUP:
      return field.message_type()->full_name();
    default:
      return field.type_name();
  }
}

void describeFields(const pb::Descriptor& d, int depth, std::vector<const pb::Descriptor*>* stack,
                    pb::RepeatedPtrField<v1::ParameterSchema>* out) {
  stack->push_back(&d);
  for (int i = 0; i < d.field_count(); ++i) {
    const FD& field = *d.field(i);
    const v1::ParameterRule& rule = ruleOf(field);
    // For a map, what the schema describes per key is its value type.
    const FD& value_field = field.is_map() ? *field.message_type()->map_value() : field;
    v1::ParameterSchema* schema = out->Add();
    schema->set_name(field.name());
    if (field.is_map()) {
      setValueType(v1::PARAMETER_TYPE_OBJECT, schema);
      schema->set_proto_type(absl::StrCat("map<", protoTypeOf(*field.message_type()->map_key()),
                                          ", ", protoTypeOf(value_field), ">"));
    } else {
      setValueType(valueTypeOf(field), schema);
      schema->set_proto_type(protoTypeOf(field));
      schema->set_repeated(field.is_repeated());
    }
    schema->set_unit(unitOfFieldName(field.name()));
    if (rule.has_range()) *schema->mutable_range() = rule.range();
    schema->set_default_json(rule.default_json());
    schema->set_required(rule.required());
    schema->set_description(descriptionOf(field, rule));
    if (value_field.cpp_type() == FD::CPPTYPE_ENUM) {
      const pb::EnumDescriptor& e = *value_field.enum_type();
      for (int j = 0; j < e.value_count(); ++j) schema->add_enum_values(e.value(j)->name());
    }
    if (value_field.cpp_type() == FD::CPPTYPE_MESSAGE) {
      const pb::Descriptor& nested = *value_field.message_type();
      const bool on_path = std::find(stack->begin(), stack->end(), &nested) != stack->end();
      if (!on_path && depth + 1 < kMaxDescribeDepth) {
        describeFields(nested, depth + 1, stack, schema->mutable_fields());
      }
    }
  }
  stack->pop_back();
}

}  // namespace

absl::Status fromStruct(const google::protobuf::Struct& in, google::protobuf::Message* out) {
  out->Clear();
  return parseMessage(in, out, "");
}

google::protobuf::Struct toStruct(const google::protobuf::Message& message) {
  return messageToStruct(message);
}

absl::Status applyDefaultsAndValidate(google::protobuf::Message* message) {
  return validateMessage(message, "");
}

void mergeUpdate(const google::protobuf::Message& update, google::protobuf::Message* current) {
  GOOGLE_CHECK_EQ(update.GetDescriptor(), current->GetDescriptor())
      << "mergeUpdate of " << update.GetDescriptor()->full_name() << " into "
      << current->GetDescriptor()->full_name();
  const pb::Reflection* ru = update.GetReflection();
  const pb::Reflection* rc = current->GetReflection();
  std::vector<const FD*> fields;
  ru->ListFields(update, &fields);
  for (const FD* field : fields) {
    if (field->is_repeated()) {
      // A list (or map) in an update is the new list, not items to add.
      rc->ClearField(current, field);
      for (int i = 0; i < ru->FieldSize(update, field); ++i) copyValue(update, *field, i, current);
    } else if (field->cpp_type() == FD::CPPTYPE_MESSAGE && rc->HasField(*current, field)) {
      mergeUpdate(ru->GetMessage(update, field), rc->MutableMessage(current, field));
    } else {
      copyValue(update, *field, -1, current);
    }
  }
}

void describe(const google::protobuf::Descriptor& descriptor,
              google::protobuf::RepeatedPtrField<v1::ParameterSchema>* out) {
  std::vector<const pb::Descriptor*> stack;
  describeFields(descriptor, 0, &stack, out);
}

std::string unitOfFieldName(std::string_view name) {
  static constexpr std::pair<absl::string_view, absl::string_view> kSuffixes[] = {
      {"_s", "s"},         {"_ms", "ms"},       {"_m", "m"},
      {"_m_s", "m/s"},     {"_m_s2", "m/s^2"},  {"_rad", "rad"},
      {"_rad_s", "rad/s"}, {"_deg", "deg"},     {"_hz", "Hz"},
      {"_n", "N"},         {"_kg", "kg"},       {"_v", "V"},
      {"_a", "A"},         {"_px", "px"},       {"_pa", "Pa"},
      {"_ratio", "1"},     {"_percent", "%"},   {"_bytes", "bytes"},
      {"_m_s3", "m/s^3"},  {"_n_s_m", "N s/m"}, {"_n_s2_m2", "N s^2/m^2"},
  };
  // This abseil build does not alias absl::string_view to std::string_view.
  const absl::string_view field_name(name.data(), name.size());
  // Longest match wins: "speed_m_s" is m/s, not s.
  absl::string_view best_suffix;
  absl::string_view unit;
  for (const auto& [suffix, suffix_unit] : kSuffixes) {
    if (field_name.size() > suffix.size() && absl::EndsWith(field_name, suffix) &&
        suffix.size() > best_suffix.size()) {
      best_suffix = suffix;
      unit = suffix_unit;
    }
  }
  return std::string(unit);
}

std::string numberText(double value) { return formatNumber(value); }

std::string rangeText(const v1::Range& range) { return describeRange(range); }

}  // namespace behaviorlib::params
