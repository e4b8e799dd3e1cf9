// The flight recorder's file format and topic mapping, without servers
// (clients/recorder, decision 36): the MCAP writer and reader round trip,
// a file cut short, malformed and oversized records, the schemas, and where
// a replay publishes each recorded message.

#include "behaviorlib/recorder/recorder.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/descriptor.pb.h>
#include <google/protobuf/descriptor_database.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "behaviorlib/v1/coordinator.pb.h"
#include "behaviorlib/v1/mission.pb.h"
#include "formats/mcap/mcap.h"

namespace behaviorlib::recorder {
namespace {

namespace fs = std::filesystem;

class McapTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("recorder_test_" + std::to_string(::getpid()) + "_" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string path(const std::string& name) const { return (dir_ / name).string(); }

  static std::string bytesOf(const std::string& file) {
    std::ifstream in(file, std::ios::binary);
    return std::string(std::istreambuf_iterator<char>(in), {});
  }
  static void writeBytes(const std::string& file, const std::string& bytes) {
    std::ofstream(file, std::ios::binary) << bytes;
  }

  // Writes three messages on two channels of two schemas.
  std::string writeSample() {
    const std::string file = path("sample.mcap");
    auto writer = mcap::Writer::create(file, "behaviorlib", "test");
    EXPECT_TRUE(writer.ok()) << writer.status();
    auto pose = (*writer)->addSchema("behaviorlib.v1.PoseStamped", "protobuf", "schema-a");
    auto event = (*writer)->addSchema("behaviorlib.v1.FleetEvent", "protobuf", "schema-b");
    EXPECT_EQ(*(*writer)->addSchema("behaviorlib.v1.PoseStamped", "protobuf", "schema-a"), *pose);
    auto poses = (*writer)->addChannel(*pose, "robots/r/ground_truth/pose", "protobuf");
    auto events = (*writer)->addChannel(*event, "coordinator/events", "protobuf", {{"k", "v"}});
    EXPECT_EQ(*(*writer)->addChannel(*pose, "robots/r/ground_truth/pose", "protobuf"), *poses);
    EXPECT_TRUE((*writer)->write(*poses, 100, 90, "first").ok());
    EXPECT_TRUE((*writer)->write(*events, 200, 190, std::string("se\0cond", 7)).ok());
    EXPECT_TRUE((*writer)->write(*poses, 300, 290, "third").ok());
    EXPECT_FALSE((*writer)->write(99, 300, 290, "nowhere").ok());
    EXPECT_EQ((*writer)->messageCount(), 3u);
    EXPECT_TRUE((*writer)->close().ok());
    return file;
  }

  static std::vector<mcap::Message> readAll(const std::string& file, mcap::ScanSummary* summary,
                                            absl::Status* status = nullptr,
                                            const mcap::ReadLimits& limits = {}) {
    std::vector<mcap::Message> messages;
    auto scanned = mcap::scan(file, limits, [&](const mcap::ScanSummary&, const mcap::Message& m) {
      messages.push_back(m);
      return true;
    });
    if (status != nullptr) *status = scanned.status();
    if (scanned.ok() && summary != nullptr) *summary = *scanned;
    return messages;
  }

  fs::path dir_;
};

TEST_F(McapTest, WhatIsWrittenIsReadBackInOrder) {
  const std::string file = writeSample();
  mcap::ScanSummary summary;
  const auto messages = readAll(file, &summary);
  EXPECT_TRUE(summary.complete);
  EXPECT_EQ(summary.profile, "behaviorlib");
  EXPECT_EQ(summary.library, "test");
  ASSERT_EQ(summary.schemas.size(), 2u);
  ASSERT_EQ(summary.channels.size(), 2u);
  ASSERT_EQ(messages.size(), 3u);
  EXPECT_EQ(messages[0].data, "first");
  EXPECT_EQ(messages[1].data, std::string("se\0cond", 7));
  EXPECT_EQ(messages[2].data, "third");
  EXPECT_EQ(messages[1].log_time_ns, 200u);
  EXPECT_EQ(messages[1].publish_time_ns, 190u);
  // Sequences count per channel.
  EXPECT_EQ(messages[0].sequence, 0u);
  EXPECT_EQ(messages[2].sequence, 1u);
  const mcap::Channel& events = summary.channels.at(messages[1].channel_id);
  EXPECT_EQ(events.topic, "coordinator/events");
  EXPECT_EQ(events.metadata.at("k"), "v");
  EXPECT_EQ(summary.schemas.at(events.schema_id).name, "behaviorlib.v1.FleetEvent");
  EXPECT_EQ(summary.schemas.at(events.schema_id).data, "schema-b");
}

TEST_F(McapTest, AFileCutShortReadsUpToItsLastWholeRecord) {
  const std::string whole = bytesOf(writeSample());
  // Cut inside the third message: what a killed recorder leaves.
  const size_t third = whole.find("third");
  ASSERT_NE(third, std::string::npos);
  writeBytes(path("cut.mcap"), whole.substr(0, third + 2));
  mcap::ScanSummary summary;
  absl::Status status;
  const auto messages = readAll(path("cut.mcap"), &summary, &status);
  ASSERT_TRUE(status.ok()) << status;
  EXPECT_FALSE(summary.complete);
  ASSERT_EQ(messages.size(), 2u);
  EXPECT_EQ(messages[1].data, std::string("se\0cond", 7));
}

TEST_F(McapTest, ARecordingJustBegunIsReadAsEmptyAndIncomplete) {
  // Created and not yet flushed past part of the magic: no messages, not
  // an error.
  writeBytes(path("new.mcap"), std::string("\x89MCA", 4));
  mcap::ScanSummary summary;
  absl::Status status;
  EXPECT_TRUE(readAll(path("new.mcap"), &summary, &status).empty());
  ASSERT_TRUE(status.ok()) << status;
  EXPECT_FALSE(summary.complete);
  writeBytes(path("empty.mcap"), "");
  readAll(path("empty.mcap"), &summary, &status);
  EXPECT_TRUE(status.ok()) << status;
  // The writer's file is an MCAP file from its creation on.
  auto writer = mcap::Writer::create(path("open.mcap"), "behaviorlib", "test");
  ASSERT_TRUE(writer.ok());
  readAll(path("open.mcap"), &summary, &status);
  ASSERT_TRUE(status.ok()) << status;
  EXPECT_EQ(summary.profile, "behaviorlib");
  EXPECT_FALSE(summary.complete);
}

TEST_F(McapTest, TheVisitorCanStopTheScan) {
  const std::string file = writeSample();
  int seen = 0;
  auto summary = mcap::scan(
      file, {}, [&](const mcap::ScanSummary&, const mcap::Message&) { return ++seen < 2; });
  ASSERT_TRUE(summary.ok());
  EXPECT_TRUE(summary->stopped);
  EXPECT_EQ(seen, 2);
}

TEST_F(McapTest, BadFilesAreRefusedWithWhereAndWhy) {
  absl::Status status;
  writeBytes(path("text.mcap"), "not an mcap file at all");
  readAll(path("text.mcap"), nullptr, &status);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(status.message().find("not an MCAP file"), std::string::npos) << status;

  readAll(path("missing.mcap"), nullptr, &status);
  EXPECT_EQ(status.code(), absl::StatusCode::kNotFound);

  // A record claiming more than the limit is refused before it is read.
  mcap::ReadLimits small;
  small.max_record_bytes = 16;
  readAll(writeSample(), nullptr, &status, small);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(status.message().find("over the limit"), std::string::npos) << status;

  mcap::ReadLimits tiny_file;
  tiny_file.max_file_bytes = 64;
  readAll(writeSample(), nullptr, &status, tiny_file);
  EXPECT_EQ(status.code(), absl::StatusCode::kResourceExhausted) << status;

  // A message whose channel never came: malformed, with the byte offset.
  std::string bytes = bytesOf(writeSample());
  const size_t first = bytes.find("first");
  // The message's channel id is 22 bytes before its data.
  bytes[first - 22] = 9;
  writeBytes(path("orphan.mcap"), bytes);
  readAll(path("orphan.mcap"), nullptr, &status);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(status.message().find("at byte"), std::string::npos) << status;
}

// The fuzz target's seeds (tests/fuzz/make_seeds.py builds them record by
// record from the spec): one whole, one in an uncompressed chunk, one cut.
TEST(McapSeedTest, TheSeedsOfOtherWritersAreRead) {
  const std::string dir = BEHAVIORLIB_MCAP_SEEDS;
  const auto count = [](const std::string& file, mcap::ScanSummary* summary) {
    int n = 0;
    auto scanned = mcap::scan(file, {}, [&](const mcap::ScanSummary&, const mcap::Message&) {
      ++n;
      return true;
    });
    EXPECT_TRUE(scanned.ok()) << file << ": " << scanned.status();
    if (scanned.ok()) *summary = *scanned;
    return n;
  };
  mcap::ScanSummary whole, chunked, cut;
  EXPECT_EQ(count(dir + "/flight.mcap", &whole), 6);
  EXPECT_TRUE(whole.complete);
  EXPECT_EQ(whole.profile, "behaviorlib");
  EXPECT_EQ(count(dir + "/flight_chunked.mcap", &chunked), 6);
  EXPECT_TRUE(chunked.complete);
  EXPECT_EQ(count(dir + "/flight_cut.mcap", &cut), 5);
  EXPECT_FALSE(cut.complete);
  // The same bytes from memory (the fuzz target's way in).
  std::ifstream in(dir + "/flight_chunked.mcap", std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), {});
  int n = 0;
  auto from_memory =
      mcap::scanBytes(bytes, {}, [&](const mcap::ScanSummary&, const mcap::Message&) {
        ++n;
        return true;
      });
  ASSERT_TRUE(from_memory.ok()) << from_memory.status();
  EXPECT_EQ(n, 6);
  EXPECT_TRUE(mcap::scanBytes("", {}, [](const auto&, const auto&) { return true; }).ok());
}

TEST(RecorderSchemaTest, ASchemaHoldsItsTypeAndEveryImportDependenciesFirst) {
  const auto schema = schemaOf("behaviorlib.v1.FleetEvent");
  ASSERT_TRUE(schema.ok()) << schema.status();
  google::protobuf::FileDescriptorSet set;
  ASSERT_TRUE(set.ParseFromString(*schema));
  // Building a pool file by file succeeds only if each file's imports came
  // before it.
  google::protobuf::DescriptorPool pool;
  for (const auto& file : set.file()) {
    ASSERT_NE(pool.BuildFile(file), nullptr) << file.name();
  }
  const auto* event = pool.FindMessageTypeByName("behaviorlib.v1.FleetEvent");
  ASSERT_NE(event, nullptr);
  EXPECT_NE(event->FindFieldByName("behavior_event"), nullptr);
  EXPECT_EQ(schemaOf("no.such.Type").status().code(), absl::StatusCode::kNotFound);
}

TEST(RecorderTopicTest, ATopicIsRecordedAtEverySampleOrAtTheRateAfterTheAt) {
  auto every = parseTopic("flight_state");
  ASSERT_TRUE(every.ok()) << every.status();
  EXPECT_EQ(every->name, "flight_state");
  EXPECT_EQ(every->max_rate_hz, 0);
  auto rated = parseTopic("ground_truth/pose@12.5");
  ASSERT_TRUE(rated.ok()) << rated.status();
  EXPECT_EQ(rated->name, "ground_truth/pose");
  EXPECT_EQ(rated->max_rate_hz, 12.5);
  for (const char* bad :
       {"pose@", "pose@0", "pose@-3", "pose@fast", "pose@1e9", "a//b", "x y", "@5"}) {
    const auto refused = parseTopic(bad);
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << bad;
    EXPECT_NE(refused.status().message().find(bad), std::string::npos) << refused.status();
  }
  // Every default parses.
  for (const std::string& entry : defaultTopics()) EXPECT_TRUE(parseTopic(entry).ok()) << entry;
}

TEST(RecorderReplayTopicTest, EachRecordedMessageHasItsBrokerTopic) {
  v1::FleetEvent event;
  event.mutable_behavior_event()->set_robot_id("drone1");
  EXPECT_EQ(replayTopic(kEventsTopic, "behaviorlib.v1.FleetEvent", event.SerializeAsString()),
            "robots/drone1/recording/events");
  v1::FleetEvent system;
  system.mutable_system_state_changed()->mutable_system()->set_robot_id("drone2");
  EXPECT_EQ(replayTopic(kEventsTopic, "behaviorlib.v1.FleetEvent", system.SerializeAsString()),
            "robots/drone2/recording/events");
  v1::MissionStatus mission;
  mission.set_robot_id("drone1");
  EXPECT_EQ(
      replayTopic(kMissionsTopic, "behaviorlib.v1.MissionStatus", mission.SerializeAsString()),
      "robots/drone1/recording/missions");
  v1::Belief belief;
  belief.set_key("drone1/markers/QR-1");
  EXPECT_EQ(replayTopic(kBeliefsTopic, "behaviorlib.v1.Belief", belief.SerializeAsString()),
            "robots/drone1/recording/beliefs");
  EXPECT_EQ(replayTopic("robots/drone1/ground_truth/pose", "behaviorlib.v1.PoseStamped", ""),
            "robots/drone1/ground_truth/pose");
  // What the broker cannot carry has no topic: no robot, a bad segment, a
  // topic of another recorder, a payload that is not its type.
  EXPECT_EQ(replayTopic(kEventsTopic, "behaviorlib.v1.FleetEvent", ""), "");
  EXPECT_EQ(replayTopic("robots/a b/pose", "behaviorlib.v1.PoseStamped", ""), "");
  EXPECT_EQ(replayTopic("/tf", "tf2_msgs.TFMessage", ""), "");
  EXPECT_EQ(replayTopic(kMissionsTopic, "behaviorlib.v1.MissionStatus", "\xff\xff"), "");
}

}  // namespace
}  // namespace behaviorlib::recorder
