// A parameter's JSON type from its schema: value_type, or the text `type` of
// a system that predates it; and whether a value has it.

#include "coordinator/common/parameter_types.h"

#include <gtest/gtest.h>

namespace behaviorlib::coordinator {
namespace {

google::protobuf::Value number(double x) {
  google::protobuf::Value v;
  v.set_number_value(x);
  return v;
}
google::protobuf::Value text(const std::string& s) {
  google::protobuf::Value v;
  v.set_string_value(s);
  return v;
}

TEST(ParameterTypes, ValueTypeWinsOverTheText) {
  v1::ParameterSchema schema;
  schema.set_type("string");
  schema.set_value_type(v1::PARAMETER_TYPE_NUMBER);
  EXPECT_EQ(valueTypeOf(schema), v1::PARAMETER_TYPE_NUMBER);
  EXPECT_TRUE(valueHasType(schema, number(1.5)));
  EXPECT_FALSE(valueHasType(schema, text("1.5")));
}

TEST(ParameterTypes, ASchemaWithoutValueTypeIsReadFromItsText) {
  const std::pair<const char*, v1::ParameterType> kTexts[] = {
      {"number", v1::PARAMETER_TYPE_NUMBER},   {"integer", v1::PARAMETER_TYPE_INTEGER},
      {"boolean", v1::PARAMETER_TYPE_BOOLEAN}, {"string", v1::PARAMETER_TYPE_STRING},
      {"enum", v1::PARAMETER_TYPE_ENUM},       {"object", v1::PARAMETER_TYPE_OBJECT},
      {"bytes", v1::PARAMETER_TYPE_BYTES},     {"tensor", v1::PARAMETER_TYPE_UNSPECIFIED}};
  for (const auto& [name, type] : kTexts) {
    v1::ParameterSchema schema;
    schema.set_type(name);
    EXPECT_EQ(valueTypeOf(schema), type) << name;
  }
  v1::ParameterSchema old_enum;
  old_enum.set_type("enum");
  EXPECT_TRUE(valueHasType(old_enum, text("SLOW")));
  EXPECT_FALSE(valueHasType(old_enum, number(1)));
  // A type it does not know: any value.
  v1::ParameterSchema unknown;
  unknown.set_type("tensor");
  EXPECT_TRUE(valueHasType(unknown, number(1)));
}

}  // namespace
}  // namespace behaviorlib::coordinator
