#include "coordinator/durable/journal.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <iterator>
#include <map>

#include "coordinator/process/replayed_state.h"

namespace behaviorlib::coordinator {
namespace {

std::string tempPath() {
  char name[] = "/tmp/journal_test_XXXXXX";
  const int fd = mkstemp(name);
  close(fd);
  std::remove(name);
  return name;
}

behaviorlib::durable::v1::JournalRecord belief(const std::string& key, double value) {
  behaviorlib::durable::v1::JournalRecord r;
  r.mutable_belief()->set_key(key);
  r.mutable_belief()->mutable_value()->set_number_value(value);
  return r;
}

std::vector<std::string> replayKeys(const std::string& path, uint64_t* truncated = nullptr) {
  std::vector<std::string> keys;
  auto journal = Journal::open(path, [&](const behaviorlib::durable::v1::JournalRecord& r) {
    keys.push_back(r.belief().key());
  });
  EXPECT_TRUE(journal.ok()) << journal.status();
  if (truncated && journal.ok()) *truncated = (*journal)->truncatedBytes();
  return keys;
}

TEST(Journal, ReplaysWhatWasAppendedInOrder) {
  const std::string path = tempPath();
  {
    auto journal = Journal::open(
        path, [](const behaviorlib::durable::v1::JournalRecord&) { FAIL() << "empty journal"; });
    ASSERT_TRUE(journal.ok());
    for (int i = 0; i < 100; ++i) {
      std::string key = "k";
      key += std::to_string(i);
      ASSERT_TRUE((*journal)->append(belief(key, i)).ok());
    }
    EXPECT_EQ((*journal)->recordCount(), 100u);
  }
  const auto keys = replayKeys(path);
  ASSERT_EQ(keys.size(), 100u);
  EXPECT_EQ(keys.front(), "k0");
  EXPECT_EQ(keys.back(), "k99");
  std::remove(path.c_str());
}

TEST(Journal, ATornLastRecordIsCutOffAndTheRestKept) {
  const std::string path = tempPath();
  {
    auto journal = Journal::open(path, [](const behaviorlib::durable::v1::JournalRecord&) {});
    ASSERT_TRUE(journal.ok());
    ASSERT_TRUE((*journal)->append(belief("a", 1)).ok());
    ASSERT_TRUE((*journal)->append(belief("b", 2)).ok());
  }
  // A crash in the middle of the third write: a length that promises more
  // bytes than follow.
  {
    std::ofstream out(path, std::ios::app | std::ios::binary);
    const char torn[] = {40, 0, 0, 0, 1, 2, 3, 4, 'x', 'y'};
    out.write(torn, sizeof torn);
  }
  uint64_t truncated = 0;
  EXPECT_EQ(replayKeys(path, &truncated), (std::vector<std::string>{"a", "b"}));
  EXPECT_EQ(truncated, 10u);
  // The cut is permanent, and appending goes on after the good records.
  {
    auto journal = Journal::open(path, [](const behaviorlib::durable::v1::JournalRecord&) {});
    ASSERT_TRUE(journal.ok());
    EXPECT_EQ((*journal)->truncatedBytes(), 0u);
    ASSERT_TRUE((*journal)->append(belief("c", 3)).ok());
  }
  EXPECT_EQ(replayKeys(path), (std::vector<std::string>{"a", "b", "c"}));
  std::remove(path.c_str());
}

TEST(Journal, ACorruptRecordEndsTheReplay) {
  const std::string path = tempPath();
  {
    auto journal = Journal::open(path, [](const behaviorlib::durable::v1::JournalRecord&) {});
    ASSERT_TRUE((*journal)->append(belief("a", 1)).ok());
    ASSERT_TRUE((*journal)->append(belief("b", 2)).ok());
  }
  {
    std::fstream f(path, std::ios::in | std::ios::out | std::ios::binary);
    f.seekp(-1, std::ios::end);
    f.put('\x7f');  // flips the last payload byte: its checksum fails
  }
  EXPECT_EQ(replayKeys(path), (std::vector<std::string>{"a"}));
  std::remove(path.c_str());
}

TEST(Journal, CompactionReplacesTheContent) {
  const std::string path = tempPath();
  {
    auto journal = Journal::open(path, [](const behaviorlib::durable::v1::JournalRecord&) {});
    for (int i = 0; i < 50; ++i) ASSERT_TRUE((*journal)->append(belief("same", i)).ok());
    const uint64_t before = (*journal)->sizeBytes();
    ASSERT_TRUE((*journal)->compact({belief("same", 49)}).ok());
    EXPECT_LT((*journal)->sizeBytes(), before / 10);
    ASSERT_TRUE((*journal)->append(belief("after", 1)).ok());
  }
  EXPECT_EQ(replayKeys(path), (std::vector<std::string>{"same", "after"}));
  std::remove(path.c_str());
}

// Online: records appended while the snapshot is read are kept after it, so
// that the last value of each key survives the compaction.
TEST(Journal, OnlineCompactionKeepsWhatIsAppendedDuringTheSnapshot) {
  const std::string path = tempPath();
  {
    auto journal = Journal::open(path, [](const behaviorlib::durable::v1::JournalRecord&) {});
    for (int i = 0; i < 50; ++i) ASSERT_TRUE((*journal)->append(belief("a", i)).ok());
    const uint64_t before = (*journal)->sizeBytes();
    ASSERT_TRUE((*journal)
                    ->compactOnline([&] {
                      // The store's state as read, while a writer goes on.
                      EXPECT_TRUE((*journal)->append(belief("a", 50)).ok());
                      EXPECT_TRUE((*journal)->append(belief("b", 1)).ok());
                      return std::vector<behaviorlib::durable::v1::JournalRecord>{belief("a", 49)};
                    })
                    .ok());
    EXPECT_LT((*journal)->sizeBytes(), before / 10);
    EXPECT_EQ((*journal)->recordCount(), 3u);
    ASSERT_TRUE((*journal)->append(belief("c", 1)).ok());
  }
  std::map<std::string, double> last;
  auto reopened = Journal::open(path, [&](const behaviorlib::durable::v1::JournalRecord& r) {
    last[r.belief().key()] = r.belief().value().number_value();
  });
  ASSERT_TRUE(reopened.ok());
  EXPECT_EQ(last, (std::map<std::string, double>{{"a", 50}, {"b", 1}, {"c", 1}}));
  std::remove(path.c_str());
}

// decodeJournal is open()'s replay over bytes in memory: the valid prefix's
// length, its records in order, and nothing past a torn or corrupt record.
TEST(Journal, DecodeJournalReturnsTheValidPrefix) {
  const std::string path = tempPath();
  {
    auto journal = Journal::open(path, [](const behaviorlib::durable::v1::JournalRecord&) {});
    ASSERT_TRUE(journal.ok());
    ASSERT_TRUE((*journal)->append(belief("a", 1)).ok());
    ASSERT_TRUE((*journal)->append(belief("b", 2)).ok());
  }
  std::string content;
  {
    std::ifstream in(path, std::ios::binary);
    content.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  std::remove(path.c_str());
  std::vector<std::string> keys;
  const auto collect = [&](const behaviorlib::durable::v1::JournalRecord& r) {
    keys.push_back(r.belief().key());
  };
  uint64_t records = 0;
  EXPECT_EQ(decodeJournal(content, collect, &records), content.size());
  EXPECT_EQ(records, 2u);
  EXPECT_EQ(keys, (std::vector<std::string>{"a", "b"}));

  // A torn tail is left out.
  keys.clear();
  const std::string torn = content + std::string("\x28\0\0\0\1\2\3\4xy", 10);
  EXPECT_EQ(decodeJournal(torn, collect, &records), content.size());
  EXPECT_EQ(records, 2u);

  // A corrupt second record ends the replay after the first.
  keys.clear();
  std::string corrupt = content;
  corrupt.back() = static_cast<char>(corrupt.back() ^ 0x7f);
  const size_t first = decodeJournal(corrupt, collect, &records);
  EXPECT_EQ(records, 1u);
  EXPECT_EQ(keys, (std::vector<std::string>{"a"}));
  EXPECT_GT(first, 8u);
  EXPECT_LT(first, content.size());

  EXPECT_EQ(decodeJournal("", collect, &records), 0u);
  EXPECT_EQ(records, 0u);
  EXPECT_EQ(decodeJournal(std::string(7, '\0'), collect), 0u);
}

TEST(ReplayedState, KeepsTheLastOfEachBeliefAndSystemAndEveryMissionStatus) {
  ReplayedState replayed;
  const auto belief = [](const std::string& key, double value, uint64_t version) {
    behaviorlib::durable::v1::JournalRecord r;
    r.mutable_belief()->set_key(key);
    r.mutable_belief()->mutable_value()->set_number_value(value);
    r.mutable_belief()->set_version(version);
    return r;
  };
  const auto system = [](const std::string& robot, const std::string& address, bool gone) {
    behaviorlib::durable::v1::JournalRecord r;
    r.mutable_system()->set_robot_id(robot);
    r.mutable_system()->set_system("basic");
    r.mutable_system()->set_address(address);
    r.mutable_system()->set_unregistered(gone);
    return r;
  };
  const auto mission = [](const std::string& id, v1::MissionState state) {
    behaviorlib::durable::v1::JournalRecord r;
    r.mutable_mission()->set_mission_id(id);
    r.mutable_mission()->set_state(state);
    return r;
  };
  replayed.apply(belief("a", 1, 1));
  replayed.apply(system("drone1", "127.0.0.1:1", false));
  replayed.apply(system("drone2", "127.0.0.1:2", false));
  replayed.apply(mission("m1", v1::MISSION_STATE_RUNNING));
  replayed.apply(belief("a", 2, 2));
  replayed.apply(system("drone1", "127.0.0.1:3", false));
  replayed.apply(system("drone2", "127.0.0.1:2", true));
  replayed.apply(mission("m1", v1::MISSION_STATE_SUCCEEDED));

  auto a = replayed.beliefs.get("a");
  ASSERT_TRUE(a.has_value());
  EXPECT_EQ(a->value().number_value(), 2);
  ASSERT_EQ(replayed.systems.size(), 1u);
  EXPECT_EQ(replayed.systems.begin()->first,
            std::make_pair(std::string("drone1"), std::string("basic")));
  EXPECT_EQ(replayed.systems.begin()->second.address(), "127.0.0.1:3");
  ASSERT_EQ(replayed.missions.size(), 2u);
  EXPECT_EQ(replayed.missions.back().state(), v1::MISSION_STATE_SUCCEEDED);
}

TEST(Journal, AnUnwritablePathIsAnError) {
  auto journal = Journal::open("/nonexistent-dir/journal",
                               [](const behaviorlib::durable::v1::JournalRecord&) {});
  ASSERT_FALSE(journal.ok());
  EXPECT_NE(std::string(journal.status().message()).find("/nonexistent-dir/journal"),
            std::string::npos);
}

}  // namespace
}  // namespace behaviorlib::coordinator
