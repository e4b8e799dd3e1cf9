// AuditLog: one JSON object per control call, appended; rotated by size so
// the log's disk use is bounded; every line stays valid JSON, also for a
// caller's bytes that are not UTF-8.

#include "behaviorlib/server_kit/audit_log.h"

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <gtest/gtest.h>
#include <prometheus/registry.h>
#include <stdlib.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

namespace behaviorlib::server_kit {
namespace {

namespace fs = std::filesystem;

class AuditLogTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string templ = (fs::temp_directory_path() / "audit-XXXXXX").string();
    ASSERT_NE(::mkdtemp(templ.data()), nullptr);
    dir_ = templ;
    path_ = (dir_ / "audit.jsonl").string();
  }
  void TearDown() override { fs::remove_all(dir_); }

  // Every line of a file, each parsed as a JSON object.
  static std::vector<google::protobuf::Struct> lines(const std::string& path) {
    std::vector<google::protobuf::Struct> out;
    std::ifstream in(path);
    for (std::string line; std::getline(in, line);) {
      google::protobuf::Struct object;
      EXPECT_TRUE(google::protobuf::util::JsonStringToMessage(line, &object).ok()) << line;
      out.push_back(object);
    }
    return out;
  }
  static std::string field(const google::protobuf::Struct& s, const std::string& name) {
    auto it = s.fields().find(name);
    return it == s.fields().end() ? "" : it->second.string_value();
  }

  prometheus::Registry registry_;
  fs::path dir_;
  std::string path_;
};

TEST_F(AuditLogTest, WritesOneJsonObjectPerCallEscapingWhatTheCallerSent) {
  auto log = AuditLog::open(path_, registry_);
  ASSERT_TRUE(log.ok()) << log.status();
  (*log)->record({"behaviorlib:operator", "/behaviorlib.v1.Coordinator/Kill", "OK", ""});
  (*log)->record({"anonymous", "/x\"\n\xff\xfe/y", "PERMISSION_DENIED", "needs \"safety\"\n"});
  const auto records = lines(path_);
  ASSERT_EQ(records.size(), 2u);
  EXPECT_EQ(field(records[0], "identity"), "behaviorlib:operator");
  EXPECT_EQ(field(records[0], "method"), "/behaviorlib.v1.Coordinator/Kill");
  EXPECT_EQ(field(records[0], "outcome"), "OK");
  EXPECT_FALSE(field(records[0], "time").empty());
  // Bytes that are not UTF-8 are kept, escaped.
  EXPECT_EQ(field(records[1], "method"), "/x\\\"\\n\\xff\\xfe/y");
  EXPECT_EQ(field(records[1], "message"), "needs \"safety\"\n");
}

TEST_F(AuditLogTest, RotatesBySizeKeepingTheNewestFiles) {
  AuditRotation rotation;
  rotation.max_bytes = 1000;
  rotation.keep = 2;
  auto log = AuditLog::open(path_, registry_, rotation);
  ASSERT_TRUE(log.ok()) << log.status();
  constexpr int kCalls = 200;  // about 20 KB: many rotations
  for (int i = 0; i < kCalls; ++i) {
    (*log)->record({"behaviorlib:operator", "/behaviorlib.v1.Coordinator/StartMission", "OK",
                    std::to_string(i)});
  }
  // Only the file and its two newest predecessors remain, each near the cap.
  EXPECT_TRUE(fs::exists(path_ + ".1"));
  EXPECT_TRUE(fs::exists(path_ + ".2"));
  EXPECT_FALSE(fs::exists(path_ + ".3"));
  size_t files = 0;
  for (const auto& entry : fs::directory_iterator(dir_)) {
    ++files;
    EXPECT_LT(fs::file_size(entry.path()), 1000u + 200u) << entry.path();
  }
  EXPECT_EQ(files, 3u);
  // Oldest to newest, the kept records are the last ones, in order, none lost
  // between files.
  std::vector<int> seen;
  for (const std::string& p : {path_ + ".2", path_ + ".1", path_}) {
    for (const auto& r : lines(p)) seen.push_back(std::stoi(field(r, "message")));
  }
  ASSERT_FALSE(seen.empty());
  EXPECT_EQ(seen.back(), kCalls - 1);
  for (size_t i = 1; i < seen.size(); ++i) EXPECT_EQ(seen[i], seen[i - 1] + 1);
  EXPECT_GE(seen.size(), 12u);  // about 6 records a file
}

TEST_F(AuditLogTest, AReopenedLogCountsWhatItAlreadyHolds) {
  AuditRotation rotation;
  rotation.max_bytes = 1000;
  rotation.keep = 1;
  std::ofstream(path_) << std::string(990, ' ') << "\n";
  auto log = AuditLog::open(path_, registry_, rotation);
  ASSERT_TRUE(log.ok()) << log.status();
  (*log)->record({"behaviorlib:operator", "/behaviorlib.v1.Coordinator/Kill", "OK", ""});
  // The file passed its cap with that record and was rotated.
  EXPECT_TRUE(fs::exists(path_ + ".1"));
  EXPECT_EQ(fs::file_size(path_), 0u);
}

TEST_F(AuditLogTest, RefusesARotationThatCannotBound) {
  AuditRotation zero;
  zero.max_bytes = 0;
  EXPECT_EQ(AuditLog::open(path_, registry_, zero).status().code(),
            absl::StatusCode::kInvalidArgument);
  AuditRotation negative;
  negative.keep = -1;
  EXPECT_EQ(AuditLog::open(path_, registry_, negative).status().code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace behaviorlib::server_kit
