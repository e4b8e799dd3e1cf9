#include "behaviorlib/channel/topic.h"

#include <google/protobuf/any.pb.h>
#include <google/protobuf/descriptor.h>
#include <gtest/gtest.h>

#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::channel {
namespace {

TEST(TopicNameTest, AcceptsClockAndRobotTopics) {
  EXPECT_TRUE(validateTopicName("clock").ok());
  EXPECT_TRUE(validateTopicName("robots/drone1/pose").ok());
  EXPECT_TRUE(validateTopicName("robots/drone_1/camera/front.rgb").ok());
  EXPECT_TRUE(validateTopicName("robots/UAV-7/a/b/c/d").ok());
}

TEST(TopicNameTest, RejectsBadNamesNamingTopicAndRule) {
  for (const char* bad :
       {"", "clocks", "Clock", "robots", "robots/", "robots/drone1", "robots/drone1/",
        "robots//pose", "/robots/drone1/pose", "robots/drone 1/pose", "robots/drone1/pose?",
        "robot/drone1/pose", "robots/drone1//pose", "robots/dr\xc3\xb6ne/pose"}) {
    absl::Status status = validateTopicName(bad);
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << "'" << bad << "'";
    EXPECT_NE(status.message().find(std::string("'") + bad + "'"), std::string::npos)
        << status.message();
    EXPECT_NE(status.message().find("robots/{robot_id}/{name}"), std::string::npos)
        << status.message();
  }
}

TEST(TopicNameTest, RejectsOverlongNames) {
  std::string name = "robots/d/" + std::string(kMaxTopicNameLength, 'x');
  EXPECT_EQ(validateTopicName(name).code(), absl::StatusCode::kInvalidArgument);
}

TEST(CheckSampleTest, AcceptsKnownTypes) {
  v1::Clock clock;
  clock.mutable_time()->set_seconds(12);
  google::protobuf::Any any;
  any.PackFrom(clock);
  const google::protobuf::Descriptor* type = nullptr;
  absl::string_view reason;
  ASSERT_TRUE(checkSample("clock", any, &type, &reason).ok());
  EXPECT_EQ(type, v1::Clock::descriptor());
}

TEST(CheckSampleTest, RejectsMissingUnknownAndMalformedSamples) {
  const google::protobuf::Descriptor* type = nullptr;
  absl::string_view reason;

  google::protobuf::Any empty;
  EXPECT_EQ(checkSample("clock", empty, &type, &reason).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(reason, reject_reason::kMissingSample);

  google::protobuf::Any unknown;
  unknown.set_type_url("type.googleapis.com/no.such.Type");
  absl::Status status = checkSample("robots/d/x", unknown, &type, &reason);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(reason, reject_reason::kUnknownType);
  EXPECT_NE(status.message().find("no.such.Type"), std::string::npos);
  EXPECT_NE(status.message().find("robots/d/x"), std::string::npos);

  // Found by fuzz_channel_sample: a bare name is known to the pool but
  // Any::UnpackTo refuses it, so no typed subscriber could read the sample.
  google::protobuf::Any bare;
  bare.set_type_url("behaviorlib.v1.Imu");
  status = checkSample("robots/d/imu", bare, &type, &reason);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(reason, reject_reason::kUnknownType);
  EXPECT_NE(status.message().find("without a '/'"), std::string::npos);

  google::protobuf::Any malformed;
  malformed.set_type_url("type.googleapis.com/behaviorlib.v1.Imu");
  malformed.set_value("\xff\xff\xff\xff\xff\xff\xff\xff\xff\xff\xff", 11);
  status = checkSample("robots/d/imu", malformed, &type, &reason);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(reason, reject_reason::kMalformedSample);
  EXPECT_NE(status.message().find("behaviorlib.v1.Imu"), std::string::npos);
}

TEST(CheckSampleTest, TypeNameOfUrl) {
  EXPECT_EQ(typeNameOfUrl("type.googleapis.com/behaviorlib.v1.Clock"), "behaviorlib.v1.Clock");
  EXPECT_EQ(typeNameOfUrl("a/b/c.D"), "c.D");
  EXPECT_EQ(typeNameOfUrl("c.D"), "c.D");
}

}  // namespace
}  // namespace behaviorlib::channel
