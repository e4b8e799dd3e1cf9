// Unit tests of the shared-memory ring (channel/shm_ring.h): one writer,
// readers in this process and in a forked child, under /dev/shm.

#include "behaviorlib/channel/shm_ring.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/mman.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <new>
#include <string>
#include <thread>

namespace behaviorlib::channel {
namespace {

using Read = ShmRing::Read;

// A name of this test process's own, unlinked when done.
class ShmRingTest : public ::testing::Test {
 protected:
  std::string name(int n) {
    std::string made = ShmRing::nameFor(getpid(), 900000 + n);
    names_.push_back(made);
    return made;
  }
  void TearDown() override {
    for (const auto& n : names_) shm_unlink(n.c_str());
  }
  std::vector<std::string> names_;
};

TEST_F(ShmRingTest, ReadsInOrderAndCountsWhatWasOverwritten) {
  auto writer = ShmRing::create(name(1), 4, 64);
  ASSERT_TRUE(writer.ok()) << writer.status();
  auto reader = ShmRing::open(name(1));
  ASSERT_TRUE(reader.ok()) << reader.status();
  EXPECT_EQ((*reader)->slotCount(), 4u);
  EXPECT_EQ((*reader)->slotBytes(), 64u);

  uint64_t next = 1;
  uint64_t dropped = 0;
  std::string bytes;
  EXPECT_EQ((*reader)->read(&next, false, &bytes, &dropped), Read::kEmpty);
  for (uint64_t seq = 1; seq <= 3; ++seq) (*writer)->write(seq, "s" + std::to_string(seq));
  for (uint64_t seq = 1; seq <= 3; ++seq) {
    ASSERT_EQ((*reader)->read(&next, false, &bytes, &dropped), Read::kSample);
    EXPECT_EQ(bytes, "s" + std::to_string(seq));
  }
  EXPECT_EQ(next, 4u);
  EXPECT_EQ(dropped, 0u);
  EXPECT_EQ((*reader)->read(&next, false, &bytes, &dropped), Read::kEmpty);

  // Ten more into four slots: the reader lost 4..9 and reads 10..13.
  for (uint64_t seq = 4; seq <= 13; ++seq) (*writer)->write(seq, "s" + std::to_string(seq));
  ASSERT_EQ((*reader)->read(&next, false, &bytes, &dropped), Read::kSample);
  EXPECT_EQ(bytes, "s10");
  EXPECT_EQ(dropped, 6u);
  // Latest only: straight to 13.
  ASSERT_EQ((*reader)->read(&next, true, &bytes, &dropped), Read::kSample);
  EXPECT_EQ(bytes, "s13");
  EXPECT_EQ(dropped, 8u);
  EXPECT_EQ((*writer)->written(), 13u);
}

TEST_F(ShmRingTest, NumbersTheWriterSkippedAreNotLosses) {
  auto writer = ShmRing::create(name(2), 8, 64);
  ASSERT_TRUE(writer.ok());
  auto reader = ShmRing::open(name(2));
  ASSERT_TRUE(reader.ok());
  (*writer)->write(2, "two");
  (*writer)->write(5, "five");
  uint64_t next = 1;
  uint64_t dropped = 0;
  std::string bytes;
  ASSERT_EQ((*reader)->read(&next, false, &bytes, &dropped), Read::kSample);
  EXPECT_EQ(bytes, "two");
  ASSERT_EQ((*reader)->read(&next, false, &bytes, &dropped), Read::kSample);
  EXPECT_EQ(bytes, "five");
  EXPECT_EQ(dropped, 0u);
  EXPECT_EQ(next, 6u);
}

TEST_F(ShmRingTest, SupersededRingIsDrainedThenTheSuccessorContinuesTheNumbers) {
  auto first = ShmRing::create(name(3), 4, 16);
  ASSERT_TRUE(first.ok());
  auto reader = ShmRing::open(name(3));
  ASSERT_TRUE(reader.ok());
  (*first)->write(1, "small");
  EXPECT_FALSE((*first)->fits(100));
  auto second = ShmRing::create(name(4), 4, 256);
  ASSERT_TRUE(second.ok());
  (*first)->supersede(name(4));
  (*second)->write(2, std::string(100, 'x'));

  uint64_t next = 1;
  uint64_t dropped = 0;
  std::string bytes;
  ASSERT_EQ((*reader)->read(&next, false, &bytes, &dropped), Read::kSample);
  EXPECT_EQ(bytes, "small");
  ASSERT_EQ((*reader)->read(&next, false, &bytes, &dropped), Read::kSuperseded);
  EXPECT_EQ((*reader)->successor(), name(4));
  auto successor = ShmRing::open((*reader)->successor());
  ASSERT_TRUE(successor.ok());
  ASSERT_EQ((*successor)->read(&next, false, &bytes, &dropped), Read::kSample);
  EXPECT_EQ(bytes.size(), 100u);
  EXPECT_EQ(dropped, 0u);

  (*second)->close();
  EXPECT_EQ((*successor)->read(&next, false, &bytes, &dropped), Read::kClosed);
}

TEST_F(ShmRingTest, ReaderInAnotherProcessSleepsUntilWritten) {
  const std::string ring_name = name(5);  // names carry the pid: taken before the fork
  auto writer = ShmRing::create(ring_name, 16, 64);
  ASSERT_TRUE(writer.ok());
  // The child's progress, so that the writer never laps it however the
  // two are scheduled.
  auto* read_count = static_cast<std::atomic<uint64_t>*>(
      mmap(nullptr, sizeof(std::atomic<uint64_t>), PROT_READ | PROT_WRITE,
           MAP_SHARED | MAP_ANONYMOUS, -1, 0));
  ASSERT_NE(read_count, MAP_FAILED);
  new (read_count) std::atomic<uint64_t>(0);
  const pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    // The child reads 200 samples in order, sleeping in wait() between.
    auto reader = ShmRing::open(ring_name);
    if (!reader.ok()) _exit(10);
    uint64_t next = 1;
    uint64_t dropped = 0;
    std::string bytes;
    while (read_count->load() < 200) {
      const uint32_t token = (*reader)->notifyToken();
      const Read r = (*reader)->read(&next, false, &bytes, &dropped);
      if (r == Read::kSample) {
        if (bytes != std::to_string(next - 1)) _exit(11);
        read_count->fetch_add(1);
      } else if (r == Read::kEmpty) {
        (*reader)->wait(token, 5'000'000'000);
      } else {
        _exit(12);
      }
    }
    _exit(dropped == 0 ? 0 : 13);
  }
  for (uint64_t seq = 1; seq <= 200; ++seq) {
    while (seq - read_count->load() > 8) {
      ASSERT_EQ(waitpid(child, nullptr, WNOHANG), 0) << "the reader exited early";
      std::this_thread::sleep_for(std::chrono::microseconds(200));
    }
    (*writer)->write(seq, std::to_string(seq));
  }
  int status = 0;
  ASSERT_EQ(waitpid(child, &status, 0), child);
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0);
  munmap(read_count, sizeof(std::atomic<uint64_t>));
}

TEST_F(ShmRingTest, WakeEndsAWait) {
  auto ring = ShmRing::create(name(6), 4, 64);
  ASSERT_TRUE(ring.ok());
  const uint32_t token = (*ring)->notifyToken();
  std::thread waker([&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    (*ring)->wake();
  });
  const auto start = std::chrono::steady_clock::now();
  (*ring)->wait(token, 30'000'000'000);
  waker.join();
  EXPECT_LT(std::chrono::steady_clock::now() - start, std::chrono::seconds(20));
}

TEST_F(ShmRingTest, RefusesWhatIsNotARing) {
  EXPECT_EQ(ShmRing::open("/etc-passwd").status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(ShmRing::open("/behaviorlib-ch-1/../x").status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(ShmRing::open(name(7)).status().code(), absl::StatusCode::kUnavailable);
  // A file of the right name but not a ring.
  const int fd = shm_open(name(8).c_str(), O_CREAT | O_RDWR, 0600);
  ASSERT_GE(fd, 0);
  ASSERT_EQ(ftruncate(fd, 4096), 0);
  close(fd);
  EXPECT_EQ(ShmRing::open(name(8)).status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(ShmRing::create(name(9), 0, 64).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(ShmRing::create(name(9), 4, 1ULL << 40).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_F(ShmRingTest, RemovesOnlyTheRingsOfWritersThatAreGone) {
  // A pid that ran and exited.
  const pid_t gone = fork();
  ASSERT_GE(gone, 0);
  if (gone == 0) _exit(0);
  ASSERT_EQ(waitpid(gone, nullptr, 0), gone);
  const std::string stale = ShmRing::nameFor(gone, 1);
  names_.push_back(stale);
  ASSERT_TRUE(ShmRing::create(stale, 4, 64).ok());
  auto mine = ShmRing::create(name(10), 4, 64);
  ASSERT_TRUE(mine.ok());
  EXPECT_GE(ShmRing::removeStale(), 1);
  EXPECT_FALSE(ShmRing::open(stale).ok());
  EXPECT_TRUE(ShmRing::open(name(10)).ok());
}

}  // namespace
}  // namespace behaviorlib::channel
