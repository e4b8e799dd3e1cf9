#include "coordinator/belief/belief_store.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdio>
#include <thread>

#include "behaviorlib/v1/types.pb.h"
#include "coordinator/durable/journal.h"

namespace behaviorlib::coordinator {
namespace {

using ::testing::HasSubstr;

google::protobuf::Value number(double v) {
  google::protobuf::Value value;
  value.set_number_value(v);
  return value;
}

google::protobuf::Value text(const std::string& s) {
  google::protobuf::Value value;
  value.set_string_value(s);
  return value;
}

TEST(BeliefStore, CountAndSizeCapsAreResourceExhaustedAndChangeNothing) {
  BeliefLimits limits;
  limits.max_beliefs = 2;
  limits.max_value_bytes = 64;
  limits.max_total_bytes = 100;
  limits.max_tombstones = 1;
  BeliefStore store(nullptr, limits);
  ASSERT_TRUE(store.write("a", text("1"), "t").ok());
  ASSERT_TRUE(store.write("b", text("2"), "t").ok());
  auto third = store.write("c", text("3"), "t");
  EXPECT_EQ(third.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(third.status().message(), HasSubstr("2 beliefs"));
  EXPECT_FALSE(store.get("c"));
  // Replacing a key is not a new belief.
  EXPECT_TRUE(store.write("a", text("one"), "t").ok());
  // One value too large, and the total.
  EXPECT_EQ(store.write("a", text(std::string(100, 'x')), "t").status().code(),
            absl::StatusCode::kResourceExhausted);
  EXPECT_EQ(store.get("a")->value().string_value(), "one");
  EXPECT_TRUE(store.write("a", text(std::string(50, 'x')), "t").ok());
  EXPECT_EQ(store.write("b", text(std::string(55, 'y')), "t").status().code(),
            absl::StatusCode::kResourceExhausted)
      << "52 + 57 bytes would pass the 100 allowed";
  // Deleting frees room; one tombstone is remembered, the older forgotten.
  ASSERT_TRUE(store.erase("a", "t").ok());
  ASSERT_TRUE(store.write("c", text("3"), "t").ok());
  ASSERT_TRUE(store.erase("b", "t").ok());
  ASSERT_TRUE(store.erase("c", "t").ok());
  size_t tombstones = 0;
  for (const auto& belief : store.snapshot()) tombstones += belief.deleted() ? 1 : 0;
  EXPECT_EQ(tombstones, 1u);
}

TEST(BeliefStore, WritesReadsListsAndDeletes) {
  BeliefStore store;
  ASSERT_TRUE(store.write("drone1/altitude_m", number(1.5), "mission:m1").ok());
  ASSERT_TRUE(store.write("drone2/altitude_m", number(2.5), "mission:m1").ok());
  auto belief = store.get("drone1/altitude_m");
  ASSERT_TRUE(belief.has_value());
  EXPECT_EQ(belief->value().number_value(), 1.5);
  EXPECT_EQ(belief->writer(), "mission:m1");
  EXPECT_EQ(belief->version(), 1u);
  EXPECT_EQ(store.list("drone1/").size(), 1u);
  EXPECT_EQ(store.list().size(), 2u);
  ASSERT_TRUE(store.erase("drone1/altitude_m", "operator").ok());
  EXPECT_FALSE(store.get("drone1/altitude_m").has_value());
  EXPECT_EQ(store.erase("drone1/altitude_m", "operator").code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(store.version(), 3u);
}

TEST(BeliefStore, RefusesBadKeysWithTheRule) {
  BeliefStore store;
  for (const char* key : {"", "a//b", "/a", "a b", "path${x}"}) {
    auto written = store.write(key, number(1), "t");
    EXPECT_EQ(written.status().code(), absl::StatusCode::kInvalidArgument) << key;
  }
  EXPECT_THAT(std::string(store.write("a b", number(1), "t").status().message()),
              HasSubstr("letters, digits"));
}

TEST(BeliefStore, TypedMessagesAreStoredAsJsonWithTheirType) {
  BeliefStore store;
  v1::Path path;
  path.add_poses()->mutable_position_m()->set_x(4.0);
  auto written = store.writeMessage("drone1/path", path, "drone1/GENERATE_PATH");
  ASSERT_TRUE(written.ok()) << written.status();
  EXPECT_EQ(written->type(), "behaviorlib.v1.Path");
  const auto& poses = written->value().struct_value().fields().at("poses");
  EXPECT_EQ(poses.list_value()
                .values(0)
                .struct_value()
                .fields()
                .at("position_m")
                .struct_value()
                .fields()
                .at("x")
                .number_value(),
            4.0);
}

TEST(BeliefStore, ResolvesBindings) {
  BeliefStore store;
  google::protobuf::Value waypoints;
  for (double x : {1.0, 2.0}) waypoints.mutable_list_value()->add_values()->set_number_value(x);
  ASSERT_TRUE(store.write("drone1/path", waypoints, "t").ok());
  ASSERT_TRUE(store.write("map_file", text("/maps/a.bt"), "t").ok());
  google::protobuf::Struct params;
  (*params.mutable_fields())["path"] = text("${belief.drone1/path}");
  (*params.mutable_fields())["note"] =
      text("saved to ${belief.map_file} and ${belief.drone1/path}");
  (*params.mutable_fields())["speed_m_s"] = number(1.0);
  auto resolved = store.resolve(params);
  ASSERT_TRUE(resolved.ok()) << resolved.status();
  EXPECT_EQ(resolved->fields().at("path").list_value().values_size(), 2);
  EXPECT_EQ(resolved->fields().at("note").string_value(), "saved to /maps/a.bt and [1,2]");
  EXPECT_EQ(resolved->fields().at("speed_m_s").number_value(), 1.0);

  (*params.mutable_fields())["missing"] = text("${belief.nowhere}");
  auto missing = store.resolve(params);
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(missing.status().message()),
              HasSubstr("belief 'nowhere' is not in memory"));
}

TEST(BeliefStore, WaitForChangesWakesOnAWrite) {
  BeliefStore store;
  ASSERT_TRUE(store.write("a", number(1), "t").ok());
  std::thread writer([&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    (void)store.write("b/x", number(2), "t");
  });
  auto changes = store.waitForChanges(1, "b/", std::chrono::seconds(5));
  writer.join();
  ASSERT_EQ(changes.size(), 1u);
  EXPECT_EQ(changes[0].key(), "b/x");
  EXPECT_TRUE(store.waitForChanges(2, "", std::chrono::milliseconds(1)).empty());
}

TEST(BeliefStore, SurvivesARestartThroughTheJournal) {
  char name[] = "/tmp/belief_journal_XXXXXX";
  close(mkstemp(name));
  {
    auto journal = Journal::open(name, [](const behaviorlib::durable::v1::JournalRecord&) {});
    ASSERT_TRUE(journal.ok());
    BeliefStore store(journal->get());
    ASSERT_TRUE(store.write("answer", text("yes"), "operator").ok());
    ASSERT_TRUE(store.write("gone", number(1), "t").ok());
    ASSERT_TRUE(store.erase("gone", "t").ok());
  }
  BeliefStore restored;
  auto journal = Journal::open(name, [&](const behaviorlib::durable::v1::JournalRecord& r) {
    if (r.has_belief()) restored.restore(r.belief());
  });
  ASSERT_TRUE(journal.ok());
  EXPECT_EQ(restored.get("answer")->value().string_value(), "yes");
  EXPECT_FALSE(restored.get("gone").has_value());
  EXPECT_EQ(restored.version(), 3u);
  std::remove(name);
}

}  // namespace
}  // namespace behaviorlib::coordinator
