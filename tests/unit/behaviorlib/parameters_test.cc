#include "behaviorlib/parameters.h"

#include <gmock/gmock.h>
#include <google/protobuf/text_format.h>
#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/message_differencer.h>
#include <gtest/gtest.h>

#include <cmath>
#include <initializer_list>
#include <limits>
#include <map>
#include <string>

#include "behaviorlib/errors/status_details.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"
#include "test_parameters.pb.h"

namespace behaviorlib::params {
namespace {

using ::google::protobuf::Struct;
using ::testing::ElementsAre;
using ::testing::HasSubstr;

namespace test = ::behaviorlib::test;

// Test inputs are written as JSON, which is how callers send them.
Struct json(const std::string& text) {
  Struct s;
  const auto status = google::protobuf::util::JsonStringToMessage(text, &s);
  EXPECT_TRUE(status.ok()) << status.ToString() << " in " << text;
  return s;
}

template <typename M>
M textProto(const std::string& text) {
  M m;
  EXPECT_TRUE(google::protobuf::TextFormat::ParseFromString(text, &m)) << text;
  return m;
}

// Runs fromStruct and expects INVALID_ARGUMENT containing `substring`.
template <typename M>
void expectFromStructError(const std::string& input, const std::string& substring) {
  M m;
  const absl::Status s = fromStruct(json(input), &m);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << input << ": " << s;
  EXPECT_THAT(std::string(s.message()), HasSubstr(substring)) << input;
}

template <typename M>
void expectValidateError(const std::string& text, const std::string& substring) {
  M m = textProto<M>(text);
  const absl::Status s = applyDefaultsAndValidate(&m);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << text << ": " << s;
  EXPECT_THAT(std::string(s.message()), HasSubstr(substring)) << text;
}

const v1::ParameterSchema* findSchema(
    const google::protobuf::RepeatedPtrField<v1::ParameterSchema>& schemas,
    const std::string& name) {
  for (const auto& s : schemas) {
    if (s.name() == name) return &s;
  }
  ADD_FAILURE() << "no schema entry " << name;
  return nullptr;
}

// --- fromStruct ----------------------------------------------------------------

TEST(FromStructTest, ParsesWaitParameters) {
  v1::WaitParameters p;
  ASSERT_TRUE(fromStruct(json(R"({"duration_s": 5})"), &p).ok());
  ASSERT_TRUE(p.has_duration_s());
  EXPECT_EQ(p.duration_s(), 5);
}

TEST(FromStructTest, AcceptsJsonNames) {
  v1::WaitParameters p;
  ASSERT_TRUE(fromStruct(json(R"({"durationS": 2.5})"), &p).ok());
  EXPECT_EQ(p.duration_s(), 2.5);
  test::AllKinds a;
  ASSERT_TRUE(fromStruct(json(R"({"camelCaseName": "x"})"), &a).ok());
  EXPECT_EQ(a.camel_case_name(), "x");
}

TEST(FromStructTest, ClearsOutputFirst) {
  v1::WaitParameters p;
  p.set_duration_s(9);
  ASSERT_TRUE(fromStruct(json("{}"), &p).ok());
  EXPECT_FALSE(p.has_duration_s());
}

TEST(FromStructTest, WrongJsonType) {
  expectFromStructError<v1::WaitParameters>(
      R"({"duration_s": "five"})",
      R"(parameter 'duration_s': expected a number, got a string ("five"))");
  expectFromStructError<test::AllKinds>(
      R"({"count": "5"})", R"(parameter 'count': expected an integer, got a string ("5"))");
  expectFromStructError<test::AllKinds>(
      R"({"enabled": 1})", "parameter 'enabled': expected a boolean, got a number (1)");
  expectFromStructError<test::AllKinds>(
      R"({"name": false})", "parameter 'name': expected a string, got a boolean (false)");
  expectFromStructError<test::AllKinds>(
      R"({"blob": 3})", "parameter 'blob': expected a base64 string, got a number (3)");
  expectFromStructError<test::AllKinds>(R"({"target": 5})",
                                        "parameter 'target': expected an object, got a number (5)");
  expectFromStructError<test::AllKinds>(R"({"target": [1]})",
                                        "parameter 'target': expected an object, got a list");
  expectFromStructError<test::AllKinds>(R"({"ids": 3})",
                                        "parameter 'ids': expected a list, got a number (3)");
  expectFromStructError<test::AllKinds>(R"({"count": {}})",
                                        "parameter 'count': expected an integer, got an object");
  expectFromStructError<test::AllKinds>(R"({"limits": [1]})",
                                        "parameter 'limits': expected an object, got a list");
}

TEST(FromStructTest, LongStringsAreCutInMessages) {
  v1::WaitParameters p;
  const absl::Status s =
      fromStruct(json(R"({"duration_s": ")" + std::string(500, 'x') + R"("})"), &p);
  EXPECT_LT(s.message().size(), 200u) << s;
  EXPECT_THAT(std::string(s.message()), HasSubstr("\"..."));
}

TEST(FromStructTest, UnknownParameter) {
  expectFromStructError<v1::WaitParameters>(
      R"({"durration_s": 5})",
      "unknown parameter 'durration_s' for behaviorlib.v1.WaitParameters; known parameters: "
      "duration_s");
  expectFromStructError<test::AllKinds>(
      R"({"target": {"z_m": 1}})",
      "unknown parameter 'target.z_m' for behaviorlib.test.Waypoint; known parameters: x_m, y_m, "
      "speed_m_s");
}

TEST(FromStructTest, NullIsRejected) {
  expectFromStructError<v1::WaitParameters>(R"({"duration_s": null})",
                                            "parameter 'duration_s': null is not accepted");
  expectFromStructError<test::AllKinds>(R"({"ids": [1, null]})",
                                        "parameter 'ids[1]': expected an integer, got null");
  expectFromStructError<test::AllKinds>(R"({"target": null})",
                                        "parameter 'target': null is not accepted");
}

TEST(FromStructTest, NonFiniteNumbersAreRejected) {
  Struct s;
  (*s.mutable_fields())["duration_s"].set_number_value(std::nan(""));
  v1::WaitParameters p;
  absl::Status status = fromStruct(s, &p);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(status.message()),
              HasSubstr("parameter 'duration_s': NaN is not a finite number"));

  (*s.mutable_fields())["duration_s"].set_number_value(std::numeric_limits<double>::infinity());
  status = fromStruct(s, &p);
  EXPECT_THAT(std::string(status.message()), HasSubstr("Infinity is not a finite number"));
}

TEST(FromStructTest, Integers) {
  test::AllKinds a;
  ASSERT_TRUE(fromStruct(json(R"({"count": 7, "big": -4611686018427387904, "small_u": 4294967295,
                                  "big_u": 1e19, "s32": -3, "f64": 12})"),
                         &a)
                  .ok());
  EXPECT_EQ(a.count(), 7);
  EXPECT_EQ(a.big(), -4611686018427387904LL);
  EXPECT_EQ(a.small_u(), 4294967295u);
  EXPECT_EQ(a.big_u(), 10000000000000000000ull);
  EXPECT_EQ(a.s32(), -3);
  EXPECT_EQ(a.f64(), 12u);

  expectFromStructError<test::AllKinds>(R"({"count": 2.5})",
                                        "parameter 'count': 2.5 is not an integer");
  expectFromStructError<test::AllKinds>(R"({"ids": [1, 2.5]})",
                                        "parameter 'ids[1]': 2.5 is not an integer");
  expectFromStructError<test::AllKinds>(R"({"small_u": -1})",
                                        "parameter 'small_u': -1 is negative, but the parameter "
                                        "is uint32 (unsigned)");
  expectFromStructError<test::AllKinds>(R"({"big_u": -2})", "parameter 'big_u': -2 is negative");
  expectFromStructError<test::AllKinds>(
      R"({"count": 3000000000})",
      "parameter 'count': 3000000000 is out of range for int32 [-2147483648, 2147483647]");
  expectFromStructError<test::AllKinds>(R"({"count": -2147483649})", "out of range for int32");
  expectFromStructError<test::AllKinds>(R"({"small_u": 4294967296})",
                                        "out of range for uint32 [0, 4294967295]");
  expectFromStructError<test::AllKinds>(R"({"big": 1e19})", "out of range for int64");
  expectFromStructError<test::AllKinds>(R"({"big_u": 2e19})", "out of range for uint64");
}

TEST(FromStructTest, Floats) {
  test::AllKinds a;
  ASSERT_TRUE(fromStruct(json(R"({"ratio": 0.1, "duration_s": 1e-3})"), &a).ok());
  EXPECT_EQ(a.ratio(), 0.1f);
  EXPECT_EQ(a.duration_s(), 1e-3);
  expectFromStructError<test::AllKinds>(R"({"ratio": 1e40})",
                                        "parameter 'ratio': 1e+40 is out of range for float");
}

TEST(FromStructTest, StringsBoolsAndBytes) {
  test::AllKinds a;
  ASSERT_TRUE(fromStruct(json(R"({"name": "héllo", "enabled": true, "blob": "aGVsbG8=",
                                  "chunks": ["AAE=", "_-8"], "flags": [true, false],
                                  "tags": ["a", "b"]})"),
                         &a)
                  .ok());
  EXPECT_EQ(a.name(), "héllo");
  EXPECT_TRUE(a.enabled());
  EXPECT_EQ(a.blob(), "hello");
  // Standard and URL-safe base64 are both accepted.
  EXPECT_THAT(a.chunks(), ElementsAre(std::string("\x00\x01", 2), std::string("\xff\xef")));
  EXPECT_THAT(a.flags(), ElementsAre(true, false));
  EXPECT_THAT(a.tags(), ElementsAre("a", "b"));
  expectFromStructError<test::AllKinds>(R"({"blob": "%%%"})",
                                        R"(parameter 'blob': "%%%" is not valid base64)");
}

TEST(FromStructTest, EnumsByNameAndNumber) {
  test::AllKinds a;
  ASSERT_TRUE(
      fromStruct(json(R"({"mode": "MEDIUM", "modes": ["SLOW", 1, "MEDIUM", 0]})"), &a).ok());
  EXPECT_EQ(a.mode(), test::MEDIUM);
  EXPECT_THAT(a.modes(), ElementsAre(test::SLOW, test::MEDIUM, test::MEDIUM, test::SLOW));
  ASSERT_TRUE(fromStruct(json(R"({"mode": 1})"), &a).ok());
  EXPECT_EQ(a.mode(), test::MEDIUM);

  expectFromStructError<test::AllKinds>(
      R"({"mode": "FAST"})", R"(parameter 'mode': unknown value "FAST"; accepted: SLOW, MEDIUM)");
  expectFromStructError<test::AllKinds>(R"({"mode": "medium"})", R"(unknown value "medium")");
  expectFromStructError<test::AllKinds>(
      R"({"modes": ["SLOW", 7]})",
      "parameter 'modes[1]': unknown value 7; accepted: SLOW (0), MEDIUM (1)");
  expectFromStructError<test::AllKinds>(R"({"mode": 0.5})",
                                        "parameter 'mode': 0.5 is not an integer");
  expectFromStructError<test::AllKinds>(
      R"({"mode": true})", "parameter 'mode': expected one of SLOW, MEDIUM, got a boolean (true)");
}

TEST(FromStructTest, NestedAndRepeatedMessages) {
  test::AllKinds a;
  ASSERT_TRUE(fromStruct(json(R"({"target": {"x_m": 1, "speed_m_s": 3},
                                  "path": {"waypoints": [{"x_m": 1}, {"x_m": 2, "y_m": -2}],
                                           "frame": "odom"}})"),
                         &a)
                  .ok());
  EXPECT_EQ(a.target().x_m(), 1);
  EXPECT_EQ(a.target().speed_m_s(), 3);
  ASSERT_EQ(a.path().waypoints_size(), 2);
  EXPECT_EQ(a.path().waypoints(1).y_m(), -2);
  EXPECT_EQ(a.path().frame(), "odom");

  expectFromStructError<test::AllKinds>(
      R"({"path": {"waypoints": [{"x_m": 1}, {"x_m": "far"}]}})",
      R"(parameter 'path.waypoints[1].x_m': expected a number, got a string ("far"))");
  expectFromStructError<test::Path>(R"({"waypoints": [{"x_m": 1}, {"x_m": true}]})",
                                    "parameter 'waypoints[1].x_m': expected a number");
  expectFromStructError<test::Path>(
      R"({"waypoints": [{"x_m": 1}, 2]})",
      "parameter 'waypoints[1]': expected an object, got a number (2)");
  expectFromStructError<test::Path>(
      R"({"waypoints": [{"xm": 1}]})",
      "unknown parameter 'waypoints[0].xm' for behaviorlib.test.Waypoint");
}

TEST(FromStructTest, Maps) {
  test::AllKinds a;
  ASSERT_TRUE(
      fromStruct(json(R"({"limits": {"a": 1.5, "b": 2}, "stops": {"3": {"x_m": 4}}})"), &a).ok());
  EXPECT_EQ(a.limits().at("a"), 1.5);
  EXPECT_EQ(a.limits().at("b"), 2);
  EXPECT_EQ(a.stops().at(3).x_m(), 4);
  expectFromStructError<test::AllKinds>(R"({"stops": {"x": {}}})",
                                        R"(parameter 'stops': key "x" is not a valid int32)");
  expectFromStructError<test::AllKinds>(R"({"limits": {"a": "high"}})",
                                        R"(parameter 'limits["a"]': expected a number)");
  expectFromStructError<test::AllKinds>(R"({"stops": {"2": {"x_m": "far"}}})",
                                        "parameter 'stops[2].x_m': expected a number");
}

TEST(FromStructTest, OneofAndDuplicates) {
  test::AllKinds a;
  ASSERT_TRUE(fromStruct(json(R"({"goal_name": "home"})"), &a).ok());
  EXPECT_EQ(a.goal_name(), "home");
  expectFromStructError<test::AllKinds>(R"({"goal_name": "home", "goal_yaw_rad": 1})",
                                        "parameters 'goal_name' and 'goal_yaw_rad' are "
                                        "alternatives (oneof goal); set only one");
  expectFromStructError<test::AllKinds>(
      R"({"camel_case_name": "a", "camelCaseName": "b"})",
      "parameter 'camel_case_name' is given twice, as 'camelCaseName' and as 'camel_case_name'");
}

// --- toStruct ------------------------------------------------------------------

TEST(ToStructTest, WritesSetFieldsOnly) {
  const auto a = textProto<test::AllKinds>(R"pb(
    big: 9007199254740993
    mode: MEDIUM
    ratio: 0.1
    blob: "hello"
    retries: 0
    target { x_m: 1 }
    ids: [ 1, 2 ]
    modes: [ SLOW, MEDIUM ]
    limits { key: "a" value: 2 }
  )pb");
  const Struct s = toStruct(a);
  const auto& f = s.fields();
  EXPECT_EQ(f.size(), 9u) << s.DebugString();
  EXPECT_EQ(f.at("big").number_value(), 9007199254740992.0);  // a number, even if inexact
  EXPECT_EQ(f.at("mode").string_value(), "MEDIUM");
  EXPECT_EQ(f.at("ratio").number_value(), 0.1);  // not 0.10000000149011612
  EXPECT_EQ(f.at("blob").string_value(), "aGVsbG8=");
  EXPECT_EQ(f.at("retries").number_value(), 0);  // explicit presence: set to zero
  EXPECT_FALSE(f.contains("count"));             // implicit presence: zero is unset
  EXPECT_FALSE(f.contains("altitude_m"));
  EXPECT_EQ(f.at("target").struct_value().fields().at("x_m").number_value(), 1);
  EXPECT_FALSE(f.at("target").struct_value().fields().contains("speed_m_s"));
  ASSERT_EQ(f.at("ids").list_value().values_size(), 2);
  EXPECT_EQ(f.at("ids").list_value().values(1).number_value(), 2);
  EXPECT_EQ(f.at("modes").list_value().values(0).string_value(), "SLOW");
  EXPECT_EQ(f.at("limits").struct_value().fields().at("a").number_value(), 2);
}

TEST(ToStructTest, UnnamedEnumNumberStaysANumber) {
  test::AllKinds a;
  a.set_mode(static_cast<test::Mode>(42));
  EXPECT_EQ(toStruct(a).fields().at("mode").number_value(), 42);
}

TEST(ToStructTest, RoundTrip) {
  const auto original = textProto<test::AllKinds>(R"pb(
    count: 4
    big: -12345678901
    small_u: 7
    big_u: 123456789012
    s32: -5
    f64: 99
    ratio: 0.25
    duration_s: 12.5
    enabled: true
    name: "n"
    blob: "\x00\xff"
    mode: MEDIUM
    target { x_m: 1 y_m: 2 speed_m_s: 0 }
    path {
      waypoints { x_m: 1 }
      waypoints { y_m: 3 }
      frame: "map"
    }
    ids: [ 3, 4 ]
    gains: [ 0.5, -1 ]
    tags: [ "a", "" ]
    modes: [ MEDIUM, SLOW ]
    flags: [ false, true ]
    chunks: [ "x", "" ]
    altitude_m: 0
    retries: 2
    tree {
      label: "root"
      children { label: "leaf" }
    }
    goal_yaw_rad: 0.5
    limits { key: "a" value: 1 }
    limits { key: "b" value: 0 }
    stops {
      key: 3
      value { x_m: 5 }
    }
    camel_case_name: "c"
  )pb");
  test::AllKinds back;
  const absl::Status s = fromStruct(toStruct(original), &back);
  ASSERT_TRUE(s.ok()) << s;
  EXPECT_TRUE(google::protobuf::util::MessageDifferencer::Equals(original, back))
      << original.DebugString() << "\nvs\n"
      << back.DebugString();
}

// --- applyDefaultsAndValidate -----------------------------------------------------

TEST(ValidateTest, WaitRequiredAndRange) {
  expectValidateError<v1::WaitParameters>(
      "",
      "parameter 'duration_s' is required: How long to wait, in seconds of the behavior's "
      "clock.");
  expectValidateError<v1::WaitParameters>("duration_s: -1",
                                          "parameter 'duration_s' = -1 is out of range [0, 86400]");
  expectValidateError<v1::WaitParameters>(
      "duration_s: 86400.5", "parameter 'duration_s' = 86400.5 is out of range [0, 86400]");
  for (const char* ok : {"duration_s: 0", "duration_s: 86400", "duration_s: 3.5"}) {
    auto p = textProto<v1::WaitParameters>(ok);
    EXPECT_TRUE(applyDefaultsAndValidate(&p).ok()) << ok;
  }
}

TEST(ValidateTest, NonFiniteRejected) {
  v1::WaitParameters p;
  p.set_duration_s(std::nan(""));
  absl::Status s = applyDefaultsAndValidate(&p);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(s.message()),
              HasSubstr("parameter 'duration_s' = NaN is not a finite number"));
  p.set_duration_s(-std::numeric_limits<double>::infinity());
  s = applyDefaultsAndValidate(&p);
  EXPECT_THAT(std::string(s.message()), HasSubstr("= -Infinity is not a finite number"));

  // Without a range too, and in repeated and float fields.
  test::AllKinds a;
  a.set_duration_s(1);
  a.add_gains(1);
  a.add_gains(std::nan(""));
  s = applyDefaultsAndValidate(&a);
  EXPECT_THAT(std::string(s.message()), HasSubstr("parameter 'gains[1]' = NaN is not a finite"));
  a.clear_gains();
  a.set_ratio(std::numeric_limits<float>::infinity());
  s = applyDefaultsAndValidate(&a);
  EXPECT_THAT(std::string(s.message()), HasSubstr("parameter 'ratio' = Infinity is not a finite"));
  a.set_ratio(0.5f);
  a.mutable_target()->set_y_m(std::nan(""));
  s = applyDefaultsAndValidate(&a);
  EXPECT_THAT(std::string(s.message()), HasSubstr("parameter 'target.y_m' = NaN"));
}

TEST(ValidateTest, AppliesDefaults) {
  auto a = textProto<test::AllKinds>(R"pb(
    duration_s: 1
    path {
      waypoints { x_m: 1 }
      waypoints { speed_m_s: 0 }
    }
  )pb");
  ASSERT_TRUE(applyDefaultsAndValidate(&a).ok());
  EXPECT_EQ(a.count(), 3);
  EXPECT_TRUE(a.enabled());
  EXPECT_EQ(a.mode(), test::MEDIUM);
  ASSERT_TRUE(a.has_altitude_m());
  EXPECT_EQ(a.altitude_m(), 1.5);
  EXPECT_FALSE(a.has_retries());  // no default: stays unset
  // Recursion into set nested messages, repeated ones included.
  EXPECT_EQ(a.path().frame(), "map");
  EXPECT_EQ(a.path().waypoints(0).speed_m_s(), 2.5);
  EXPECT_EQ(a.path().waypoints(1).speed_m_s(), 0);  // explicitly set: kept
  // Unset nested messages are not created.
  EXPECT_FALSE(a.has_target());
}

TEST(ValidateTest, DefaultsDoNotOverrideSetValues) {
  auto a = textProto<test::AllKinds>("duration_s: 1 count: 9 altitude_m: 0 enabled: false");
  ASSERT_TRUE(applyDefaultsAndValidate(&a).ok());
  EXPECT_EQ(a.count(), 9);
  EXPECT_EQ(a.altitude_m(), 0);  // explicit presence: a set zero is kept
  // Implicit presence cannot tell false from unset: the default applies.
  EXPECT_TRUE(a.enabled());
}

TEST(ValidateTest, DefaultOnOneofMemberKeepsTheCallersChoice) {
  test::Choice c;
  c.set_b("x");
  ASSERT_TRUE(applyDefaultsAndValidate(&c).ok());
  EXPECT_EQ(c.b(), "x");
  test::Choice empty;
  ASSERT_TRUE(applyDefaultsAndValidate(&empty).ok());
  EXPECT_EQ(empty.a_m(), 1);
}

TEST(ValidateTest, RequiredInTestMessage) {
  test::AllKinds a;
  const absl::Status s = applyDefaultsAndValidate(&a);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(s.message()), HasSubstr("parameter 'duration_s' is required: How long."));
}

TEST(ValidateTest, Ranges) {
  expectValidateError<test::AllKinds>("duration_s: 1 count: 11",
                                      "parameter 'count' = 11 is out of range [0, 10]");
  expectValidateError<test::AllKinds>("duration_s: -1",
                                      "parameter 'duration_s' = -1 is out of range [0, +inf)");
  expectValidateError<test::AllKinds>("duration_s: 1 ids: [ 5, 0 ]",
                                      "parameter 'ids[1]' = 0 is out of range [1, 99]");
  expectValidateError<test::AllKinds>("duration_s: 1 gains: [ 11 ]",
                                      "parameter 'gains[0]' = 11 is out of range (-inf, 10]");
  expectValidateError<test::AllKinds>("duration_s: 1 ratio: 1.5",
                                      "parameter 'ratio' = 1.5 is out of range [0, 1]");
  expectValidateError<test::AllKinds>("duration_s: 1 altitude_m: 121",
                                      "parameter 'altitude_m' = 121 is out of range [0, 120]");
  expectValidateError<test::AllKinds>(
      "duration_s: 1 path { waypoints { x_m: 1 } waypoints { x_m: 200 } }",
      "parameter 'path.waypoints[1].x_m' = 200 is out of range [-100, 100]");
  expectValidateError<test::Path>(
      "waypoints { } waypoints { speed_m_s: 21 }",
      "parameter 'waypoints[1].speed_m_s' = 21 is out of range [0, 20]");
  expectValidateError<test::AllKinds>(R"pb(duration_s: 1
                                           limits { key: "a" value: -1 })pb",
                                      R"(parameter 'limits["a"]' = -1 is out of range [0, +inf))");
  expectValidateError<test::AllKinds>(
      "duration_s: 1 stops { key: 3 value { x_m: -101 } }",
      "parameter 'stops[3].x_m' = -101 is out of range [-100, 100]");
  // An implicit-presence zero is the value the behavior would use: checked.
  expectValidateError<test::Strict>("", "parameter 'level' = 0 is out of range [1, 5]");
  auto ok = textProto<test::AllKinds>(
      "duration_s: 1e9 count: 10 ids: [ 1, 99 ] gains: [ -1e9, 10 ] ratio: 1 altitude_m: 120");
  const absl::Status s = applyDefaultsAndValidate(&ok);
  EXPECT_TRUE(s.ok()) << s;
}

TEST(ValidateTest, RequiredImplicitPresenceZeroCountsAsUnset) {
  // Without explicit presence a zero cannot be told from "not given": a
  // required field must be `optional` in the .proto to accept zero.
  expectValidateError<test::AllKinds>("duration_s: 0", "parameter 'duration_s' is required");
}

TEST(ValidateTest, BadDefaultIsASchemaError) {
  test::BadDefault b;
  const absl::Status s = applyDefaultsAndValidate(&b);
  EXPECT_EQ(s.code(), absl::StatusCode::kInternal);
  EXPECT_THAT(std::string(s.message()), HasSubstr("schema error in behaviorlib.test.BadDefault.n"));
  EXPECT_THAT(std::string(s.message()), HasSubstr("expected an integer"));
}

// --- mergeUpdate ---------------------------------------------------------------

TEST(MergeUpdateTest, ReplacesSetFieldsAndKeepsOthers) {
  auto current = textProto<test::AllKinds>(R"pb(
    count: 5
    name: "x"
    ids: [ 1, 2 ]
    altitude_m: 3
    goal_yaw_rad: 1
    target { x_m: 1 y_m: 2 }
    path {
      waypoints { x_m: 1 }
      frame: "map"
    }
    limits { key: "a" value: 1 }
    limits { key: "b" value: 2 }
    modes: [ SLOW ]
    chunks: [ "c" ]
  )pb");
  const auto update = textProto<test::AllKinds>(R"pb(
    ids: [ 9 ]
    altitude_m: 0
    goal_name: "home"
    target { y_m: 7 }
    path { frame: "odom" }
    limits { key: "c" value: 3 }
    mode: MEDIUM
  )pb");
  mergeUpdate(update, &current);
  const auto expected = textProto<test::AllKinds>(R"pb(
    count: 5
    name: "x"
    ids: [ 9 ]
    altitude_m: 0
    goal_name: "home"
    target { x_m: 1 y_m: 7 }
    path {
      waypoints { x_m: 1 }
      frame: "odom"
    }
    limits { key: "c" value: 3 }
    modes: [ SLOW ]
    chunks: [ "c" ]
    mode: MEDIUM
  )pb");
  EXPECT_TRUE(google::protobuf::util::MessageDifferencer::Equals(expected, current))
      << current.DebugString();
}

TEST(MergeUpdateTest, CopiesNestedMessageWhenCurrentHasNone) {
  test::AllKinds current;
  const auto update = textProto<test::AllKinds>("target { x_m: 4 } path { waypoints { y_m: 1 } }");
  mergeUpdate(update, &current);
  EXPECT_EQ(current.target().x_m(), 4);
  ASSERT_EQ(current.path().waypoints_size(), 1);
  EXPECT_EQ(current.path().waypoints(0).y_m(), 1);
}

TEST(MergeUpdateTest, WaitUnsetKeepsCurrent) {
  v1::WaitParameters current;
  current.set_duration_s(10);
  mergeUpdate(v1::WaitParameters(), &current);
  EXPECT_EQ(current.duration_s(), 10);
  v1::WaitParameters update;
  update.set_duration_s(0);
  mergeUpdate(update, &current);
  ASSERT_TRUE(current.has_duration_s());
  EXPECT_EQ(current.duration_s(), 0);
}

// --- describe ------------------------------------------------------------------

TEST(DescribeTest, WaitParameters) {
  google::protobuf::RepeatedPtrField<v1::ParameterSchema> out;
  describe(*v1::WaitParameters::descriptor(), &out);
  ASSERT_EQ(out.size(), 1);
  const v1::ParameterSchema& d = out[0];
  EXPECT_EQ(d.name(), "duration_s");
  EXPECT_EQ(d.type(), "number");
  EXPECT_EQ(d.value_type(), v1::PARAMETER_TYPE_NUMBER);
  EXPECT_EQ(d.proto_type(), "double");
  EXPECT_FALSE(d.repeated());
  EXPECT_EQ(d.unit(), "s");
  ASSERT_TRUE(d.has_range());
  ASSERT_TRUE(d.range().has_min());
  EXPECT_EQ(d.range().min(), 0);
  EXPECT_EQ(d.range().max(), 86400);
  EXPECT_TRUE(d.required());
  EXPECT_EQ(d.description(), "How long to wait, in seconds of the behavior's clock.");
  EXPECT_EQ(d.default_json(), "");
  EXPECT_TRUE(d.enum_values().empty());
  EXPECT_TRUE(d.fields().empty());
}

TEST(DescribeTest, AllKinds) {
  google::protobuf::RepeatedPtrField<v1::ParameterSchema> out;
  describe(*test::AllKinds::descriptor(), &out);
  ASSERT_EQ(out.size(), test::AllKinds::descriptor()->field_count());
  EXPECT_EQ(out[0].name(), "count");  // declaration order

  struct Expected {
    const char* name;
    const char* type;
    const char* proto_type;
    bool repeated;
  };
  // value_type, and `type` as its text form.
  const std::map<std::string, v1::ParameterType> value_types = {
      {"integer", v1::PARAMETER_TYPE_INTEGER}, {"number", v1::PARAMETER_TYPE_NUMBER},
      {"boolean", v1::PARAMETER_TYPE_BOOLEAN}, {"string", v1::PARAMETER_TYPE_STRING},
      {"bytes", v1::PARAMETER_TYPE_BYTES},     {"enum", v1::PARAMETER_TYPE_ENUM},
      {"object", v1::PARAMETER_TYPE_OBJECT}};
  for (const Expected& e : std::initializer_list<Expected>{
           {"count", "integer", "int32", false},
           {"big", "integer", "int64", false},
           {"small_u", "integer", "uint32", false},
           {"big_u", "integer", "uint64", false},
           {"s32", "integer", "sint32", false},
           {"f64", "integer", "fixed64", false},
           {"ratio", "number", "float", false},
           {"duration_s", "number", "double", false},
           {"enabled", "boolean", "bool", false},
           {"name", "string", "string", false},
           {"blob", "bytes", "bytes", false},
           {"mode", "enum", "behaviorlib.test.Mode", false},
           {"target", "object", "behaviorlib.test.Waypoint", false},
           {"ids", "integer", "int32", true},
           {"modes", "enum", "behaviorlib.test.Mode", true},
           {"chunks", "bytes", "bytes", true},
           {"limits", "object", "map<string, double>", false},
           {"stops", "object", "map<int32, behaviorlib.test.Waypoint>", false},
       }) {
    const v1::ParameterSchema* s = findSchema(out, e.name);
    ASSERT_NE(s, nullptr);
    EXPECT_EQ(s->type(), e.type) << e.name;
    EXPECT_EQ(s->value_type(), value_types.at(e.type)) << e.name;
    EXPECT_EQ(s->proto_type(), e.proto_type) << e.name;
    EXPECT_EQ(s->repeated(), e.repeated) << e.name;
  }

  const v1::ParameterSchema* count = findSchema(out, "count");
  EXPECT_EQ(count->default_json(), "3");
  EXPECT_EQ(count->description(), "How many.");
  EXPECT_EQ(count->range().max(), 10);
  EXPECT_EQ(count->unit(), "");
  EXPECT_FALSE(count->required());

  const v1::ParameterSchema* mode = findSchema(out, "mode");
  EXPECT_THAT(mode->enum_values(), ElementsAre("SLOW", "MEDIUM"));
  EXPECT_EQ(mode->default_json(), "\"MEDIUM\"");
  EXPECT_THAT(findSchema(out, "modes")->enum_values(), ElementsAre("SLOW", "MEDIUM"));

  const v1::ParameterSchema* gains = findSchema(out, "gains");
  EXPECT_FALSE(gains->range().has_min());
  EXPECT_EQ(gains->range().max(), 10);
  EXPECT_FALSE(findSchema(out, "name")->has_range());

  EXPECT_EQ(findSchema(out, "goal_yaw_rad")->unit(), "rad");
  EXPECT_EQ(findSchema(out, "altitude_m")->unit(), "m");

  const v1::ParameterSchema* target = findSchema(out, "target");
  ASSERT_EQ(target->fields_size(), 3);
  EXPECT_EQ(target->fields(0).name(), "x_m");
  EXPECT_EQ(target->fields(0).value_type(), v1::PARAMETER_TYPE_NUMBER);
  EXPECT_EQ(target->fields(0).unit(), "m");
  EXPECT_EQ(target->fields(0).description(), "East position.");
  EXPECT_EQ(target->fields(2).unit(), "m/s");
  EXPECT_EQ(target->fields(2).default_json(), "2.5");

  const v1::ParameterSchema* path = findSchema(out, "path");
  ASSERT_EQ(path->fields_size(), 2);
  EXPECT_TRUE(path->fields(0).repeated());
  EXPECT_EQ(path->fields(0).fields_size(), 3);

  EXPECT_EQ(findSchema(out, "stops")->fields_size(), 3);
  EXPECT_TRUE(findSchema(out, "limits")->fields().empty());

  // Recursive type: described once, not again inside itself.
  const v1::ParameterSchema* tree = findSchema(out, "tree");
  ASSERT_EQ(tree->fields_size(), 2);
  EXPECT_EQ(tree->fields(1).name(), "children");
  EXPECT_EQ(tree->fields(1).proto_type(), "behaviorlib.test.Tree");
  EXPECT_TRUE(tree->fields(1).fields().empty());
}

TEST(DescribeTest, StopsAtDepthEight) {
  google::protobuf::RepeatedPtrField<v1::ParameterSchema> out;
  describe(*test::L1::descriptor(), &out);
  int levels = 0;
  const google::protobuf::RepeatedPtrField<v1::ParameterSchema>* level = &out;
  while (!level->empty()) {
    ++levels;
    level = &(*level)[0].fields();
  }
  EXPECT_EQ(levels, 8);
}

// --- unitOfFieldName -------------------------------------------------------------

TEST(UnitOfFieldNameTest, SuffixTable) {
  EXPECT_EQ(unitOfFieldName("duration_s"), "s");
  EXPECT_EQ(unitOfFieldName("timeout_ms"), "ms");
  EXPECT_EQ(unitOfFieldName("altitude_m"), "m");
  EXPECT_EQ(unitOfFieldName("speed_m_s"), "m/s");
  EXPECT_EQ(unitOfFieldName("accel_m_s2"), "m/s^2");
  EXPECT_EQ(unitOfFieldName("yaw_rad"), "rad");
  EXPECT_EQ(unitOfFieldName("yaw_rate_rad_s"), "rad/s");
  EXPECT_EQ(unitOfFieldName("heading_deg"), "deg");
  EXPECT_EQ(unitOfFieldName("rate_hz"), "Hz");
  EXPECT_EQ(unitOfFieldName("thrust_n"), "N");
  EXPECT_EQ(unitOfFieldName("payload_kg"), "kg");
  EXPECT_EQ(unitOfFieldName("battery_v"), "V");
  EXPECT_EQ(unitOfFieldName("current_a"), "A");
  EXPECT_EQ(unitOfFieldName("offset_px"), "px");
  EXPECT_EQ(unitOfFieldName("pressure_pa"), "Pa");
  EXPECT_EQ(unitOfFieldName("fill_ratio"), "1");
  EXPECT_EQ(unitOfFieldName("battery_percent"), "%");
  EXPECT_EQ(unitOfFieldName("buffer_bytes"), "bytes");
  EXPECT_EQ(unitOfFieldName("jerk_m_s3"), "m/s^3");
  EXPECT_EQ(unitOfFieldName("linear_drag_n_s_m"), "N s/m");
  EXPECT_EQ(unitOfFieldName("quadratic_drag_n_s2_m2"), "N s^2/m^2");
}

TEST(UnitOfFieldNameTest, NoUnit) {
  EXPECT_EQ(unitOfFieldName("count"), "");
  EXPECT_EQ(unitOfFieldName("items"), "");  // "s" without the underscore
  EXPECT_EQ(unitOfFieldName("_s"), "");     // a suffix alone is no name
  EXPECT_EQ(unitOfFieldName(""), "");
  EXPECT_EQ(unitOfFieldName("mode"), "");
}

// --- error details (errors.proto) ---------------------------------------------

// The reason and the one field violation of a refusal.
void expectDetails(const absl::Status& s, const std::string& reason, const std::string& field) {
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(errors::reasonOf(s), reason) << s;
  auto bad = errors::badRequest(s);
  ASSERT_TRUE(bad.has_value()) << s;
  ASSERT_EQ(bad->field_violations_size(), 1) << s;
  EXPECT_EQ(bad->field_violations(0).field(), field) << s;
  EXPECT_EQ(bad->field_violations(0).description(), s.message());
}

TEST(ErrorDetailsTest, RefusalsNameTheFieldAndTheReason) {
  auto wait = textProto<v1::WaitParameters>("duration_s: -1");
  expectDetails(applyDefaultsAndValidate(&wait), "PARAMETER_OUT_OF_RANGE", "duration_s");
  wait.Clear();
  expectDetails(applyDefaultsAndValidate(&wait), "PARAMETER_INVALID", "duration_s");

  test::AllKinds a;
  expectDetails(fromStruct(json(R"({"target": {"z_m": 1}})"), &a), "PARAMETER_INVALID",
                "target.z_m");
  expectDetails(fromStruct(json(R"({"count": 3000000000})"), &a), "PARAMETER_OUT_OF_RANGE",
                "count");
  expectDetails(fromStruct(json(R"({"path": {"waypoints": [{"x_m": 1}, {"x_m": "far"}]}})"), &a),
                "PARAMETER_INVALID", "path.waypoints[1].x_m");
  a.Clear();
  a.set_duration_s(1);
  a.add_ids(5);
  a.add_ids(100);
  expectDetails(applyDefaultsAndValidate(&a), "PARAMETER_OUT_OF_RANGE", "ids[1]");
}

}  // namespace
}  // namespace behaviorlib::params
