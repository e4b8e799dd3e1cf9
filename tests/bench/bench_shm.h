#pragma once

// Shared-memory stamps between bench_behavior_system (the probes) and
// system_bench (the client). The client creates a small file, names it in the
// BEHAVIORLIB_BENCH_SHM environment variable, and both processes mmap it.
// Stamps are CLOCK_MONOTONIC nanoseconds, which every process on the host
// shares, so a stamp taken in one process can be subtracted from one taken in
// the other.
//
// Each stamp is written first and its sequence counter incremented after
// (release); a reader waits for the counter to pass the value it saw before
// its request (acquire) and then reads the stamp.

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include <atomic>
#include <cstdint>
#include <string>

namespace behaviorlib::bench {

inline constexpr char kShmEnv[] = "BEHAVIORLIB_BENCH_SHM";
inline constexpr int kProbeCount = 7;
inline constexpr uint64_t kShmMagic = 0x6265686176626e63ULL;  // "behavbnc"

static_assert(std::atomic<uint64_t>::is_always_lock_free);
static_assert(std::atomic<int64_t>::is_always_lock_free);

/// One probe behavior's stamps.
struct alignas(64) ProbeSlot {
  /// Incremented after first_execute_ns is written (once per activation).
  std::atomic<uint64_t> first_execute_seq;
  /// When the first onExecute of the latest activation started.
  std::atomic<int64_t> first_execute_ns;
  /// Incremented after goal_ns is written.
  std::atomic<uint64_t> goal_seq;
  /// When checkGoal of the latest activation returned "finish".
  std::atomic<int64_t> goal_ns;
};

struct SharedStamps {
  uint64_t magic;
  ProbeSlot probes[kProbeCount];
};

/// CLOCK_MONOTONIC in nanoseconds.
inline int64_t monotonicNs() {
  timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<int64_t>(ts.tv_sec) * 1000000000LL + ts.tv_nsec;
}

/// Maps `path` (creating and sizing it when `create`); nullptr on failure.
inline SharedStamps* mapSharedStamps(const std::string& path, bool create) {
  const int fd = open(path.c_str(), create ? (O_RDWR | O_CREAT | O_TRUNC) : O_RDWR, 0600);
  if (fd < 0) return nullptr;
  if (create && ftruncate(fd, sizeof(SharedStamps)) != 0) {
    close(fd);
    return nullptr;
  }
  struct stat st;
  if (fstat(fd, &st) != 0 || static_cast<size_t>(st.st_size) < sizeof(SharedStamps)) {
    close(fd);
    return nullptr;
  }
  void* p = mmap(nullptr, sizeof(SharedStamps), PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  close(fd);
  if (p == MAP_FAILED) return nullptr;
  auto* stamps = static_cast<SharedStamps*>(p);
  if (create) stamps->magic = kShmMagic;  // the file is zero-filled: atomics start at 0
  return stamps;
}

}  // namespace behaviorlib::bench
