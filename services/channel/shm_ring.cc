#include "behaviorlib/channel/shm_ring.h"

#include <dirent.h>
#include <fcntl.h>
#include <linux/futex.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#include <cerrno>
#include <climits>
#include <cstring>
#include <fstream>
#include <new>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"

namespace behaviorlib::channel {
namespace {

constexpr uint64_t kMagic = 0x676e69526c684362ULL;  // "bChlRing"
constexpr uint32_t kVersion = 1;
constexpr uint32_t kMaxSlots = 1024;
constexpr uint64_t kMaxSlotBytes = 64ULL << 20;
constexpr absl::string_view kPrefix = "behaviorlib-ch-";
constexpr std::size_t kSuccessorBytes = 96;

enum State : uint32_t { kOpen = 0, kSuperseded = 1, kClosedState = 2 };

struct SlotHeader {
  // Sequence lock: 2*seq once sample `seq` is complete, odd while written.
  std::atomic<uint64_t> stamp;
  std::atomic<uint64_t> length;
};
constexpr std::size_t kSlotHeaderBytes = 16;
static_assert(sizeof(SlotHeader) == kSlotHeaderBytes);

uint64_t strideFor(uint64_t slot_bytes) { return (kSlotHeaderBytes + slot_bytes + 63) & ~63ULL; }

long futex(std::atomic<uint32_t>* word, int op, uint32_t value, const timespec* timeout) {
  return syscall(SYS_futex, reinterpret_cast<uint32_t*>(word), op, value, timeout, nullptr, 0);
}

absl::Status errnoStatus(absl::string_view what, const std::string& name) {
  return absl::UnavailableError(absl::StrCat(what, " ", name, ": ", std::strerror(errno)));
}

}  // namespace

struct ShmRing::Header {
  uint64_t magic;
  uint32_t version;
  uint32_t slot_count;
  uint64_t slot_bytes;
  uint64_t stride;
  std::atomic<uint64_t> written;
  std::atomic<uint32_t> notify;
  std::atomic<uint32_t> sleepers;
  std::atomic<uint32_t> state;
  char successor[kSuccessorBytes];
};
static_assert(std::atomic<uint64_t>::is_always_lock_free);
static_assert(std::atomic<uint32_t>::is_always_lock_free);

namespace {
constexpr std::size_t kHeaderBytes = 256;
}  // namespace

std::string ShmRing::nameFor(int64_t writer_pid, uint64_t n) {
  return absl::StrCat("/", kPrefix, writer_pid, "-", n);
}

ShmRing::ShmRing(std::string name, void* base, std::size_t size)
    : name_(std::move(name)), base_(base), size_(size) {}

ShmRing::~ShmRing() { munmap(base_, size_); }

ShmRing::Header& ShmRing::header() const { return *static_cast<Header*>(base_); }

unsigned char* ShmRing::slot(uint64_t seq) const {
  const Header& h = header();
  return static_cast<unsigned char*>(base_) + kHeaderBytes + (seq % h.slot_count) * h.stride;
}

uint32_t ShmRing::slotCount() const { return header().slot_count; }
uint64_t ShmRing::slotBytes() const { return header().slot_bytes; }
uint64_t ShmRing::written() const { return header().written.load(std::memory_order_acquire); }

absl::StatusOr<std::unique_ptr<ShmRing>> ShmRing::create(const std::string& name,
                                                         uint32_t slot_count, uint64_t slot_bytes) {
  static_assert(sizeof(Header) <= kHeaderBytes);
  if (slot_count == 0 || slot_count > kMaxSlots || slot_bytes == 0 || slot_bytes > kMaxSlotBytes) {
    return absl::InvalidArgumentError(absl::StrCat(
        "ring ", name, ": ", slot_count, " slots of ", slot_bytes, " bytes is out of range (1..",
        kMaxSlots, " slots of 1..", kMaxSlotBytes, " bytes)"));
  }
  const uint64_t stride = strideFor(slot_bytes);
  const std::size_t size = kHeaderBytes + slot_count * stride;
  shm_unlink(name.c_str());
  const int fd = shm_open(name.c_str(), O_CREAT | O_EXCL | O_RDWR, 0600);
  if (fd < 0) return errnoStatus("cannot create the shared-memory ring", name);
  // Reserved now: a full /dev/shm must fail here, not with SIGBUS at the
  // first write into a page it could not supply.
  if (const int error = posix_fallocate(fd, 0, static_cast<off_t>(size)); error != 0) {
    errno = error;
    absl::Status status = errnoStatus("cannot reserve the shared-memory ring", name);
    ::close(fd);
    shm_unlink(name.c_str());
    return status;
  }
  void* base = mmap(nullptr, size, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  ::close(fd);
  if (base == MAP_FAILED) {
    absl::Status status = errnoStatus("cannot map the shared-memory ring", name);
    shm_unlink(name.c_str());
    return status;
  }
  // Reserved zero-filled: every slot's stamp is 0 (no sample).
  auto* h = new (base) Header{};
  h->slot_count = slot_count;
  h->slot_bytes = slot_bytes;
  h->stride = stride;
  h->version = kVersion;
  std::atomic_thread_fence(std::memory_order_release);
  h->magic = kMagic;
  return std::unique_ptr<ShmRing>(new ShmRing(name, base, size));
}

absl::StatusOr<std::unique_ptr<ShmRing>> ShmRing::open(const std::string& name) {
  if (!absl::StartsWith(name, absl::StrCat("/", kPrefix)) ||
      name.find('/', 1) != std::string::npos) {
    return absl::InvalidArgumentError(absl::StrCat("'", name, "' is not a channel ring name"));
  }
  const int fd = shm_open(name.c_str(), O_RDWR, 0);
  if (fd < 0) return errnoStatus("cannot open the shared-memory ring", name);
  struct stat st {};
  if (fstat(fd, &st) != 0 || static_cast<std::size_t>(st.st_size) < kHeaderBytes) {
    ::close(fd);
    return absl::FailedPreconditionError(absl::StrCat("ring ", name, " is too small"));
  }
  const auto size = static_cast<std::size_t>(st.st_size);
  void* base = mmap(nullptr, size, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  ::close(fd);
  if (base == MAP_FAILED) return errnoStatus("cannot map the shared-memory ring", name);
  auto ring = std::unique_ptr<ShmRing>(new ShmRing(name, base, size));
  const Header& h = ring->header();
  if (h.magic != kMagic || h.version != kVersion || h.slot_count == 0 || h.slot_count > kMaxSlots ||
      h.slot_bytes > kMaxSlotBytes || h.stride != strideFor(h.slot_bytes) ||
      kHeaderBytes + h.slot_count * h.stride > size) {
    return absl::FailedPreconditionError(
        absl::StrCat("ring ", name, " is not a version-", kVersion, " channel ring"));
  }
  return ring;
}

int ShmRing::removeStale() {
  DIR* dir = opendir("/dev/shm");
  if (dir == nullptr) return 0;
  int removed = 0;
  while (const dirent* entry = readdir(dir)) {
    absl::string_view file = entry->d_name;
    if (!absl::ConsumePrefix(&file, kPrefix)) continue;
    const std::size_t dash = file.find('-');
    int64_t pid = 0;
    if (dash == absl::string_view::npos || !absl::SimpleAtoi(file.substr(0, dash), &pid) ||
        pid <= 0) {
      continue;
    }
    if (kill(static_cast<pid_t>(pid), 0) == 0 || errno != ESRCH) continue;
    if (shm_unlink(absl::StrCat("/", entry->d_name).c_str()) == 0) ++removed;
  }
  closedir(dir);
  return removed;
}

const std::string& ShmRing::domain() {
  static const std::string domain = [] {
    std::ifstream in("/proc/sys/kernel/random/boot_id");
    std::string boot_id;
    std::getline(in, boot_id);
    struct stat ns {};
    if (boot_id.empty() || stat("/proc/self/ns/ipc", &ns) != 0) return std::string();
    return absl::StrCat(boot_id, "/", static_cast<uint64_t>(ns.st_ino));
  }();
  return domain;
}

void ShmRing::write(uint64_t seq, absl::string_view bytes) {
  Header& h = header();
  unsigned char* s = slot(seq);
  auto* sh = reinterpret_cast<SlotHeader*>(s);
  sh->stamp.store(2 * seq + 1, std::memory_order_relaxed);
  std::atomic_thread_fence(std::memory_order_release);
  sh->length.store(bytes.size(), std::memory_order_relaxed);
  std::memcpy(s + kSlotHeaderBytes, bytes.data(), bytes.size());
  sh->stamp.store(2 * seq, std::memory_order_release);
  h.written.store(seq, std::memory_order_release);
  h.notify.fetch_add(1, std::memory_order_seq_cst);
  if (h.sleepers.load(std::memory_order_seq_cst) > 0) {
    futex(&h.notify, FUTEX_WAKE, INT_MAX, nullptr);
  }
}

void ShmRing::supersede(const std::string& successor) {
  Header& h = header();
  std::strncpy(h.successor, successor.c_str(), kSuccessorBytes - 1);
  h.state.store(kSuperseded, std::memory_order_release);
  wake();
}

void ShmRing::close() {
  header().state.store(kClosedState, std::memory_order_release);
  wake();
}

void ShmRing::unlink() { shm_unlink(name_.c_str()); }

std::string ShmRing::successor() const {
  const Header& h = header();
  if (h.state.load(std::memory_order_acquire) != kSuperseded) return "";
  return std::string(h.successor, strnlen(h.successor, kSuccessorBytes));
}

ShmRing::Read ShmRing::read(uint64_t* next, bool latest_only, std::string* bytes,
                            uint64_t* dropped) const {
  const Header& h = header();
  while (true) {
    // The state before `written`: a superseded or closed ring got its last
    // sample before its state changed.
    const uint32_t state = h.state.load(std::memory_order_acquire);
    const uint64_t written = h.written.load(std::memory_order_acquire);
    if (*next > written || written == 0) {
      if (state == kSuperseded) return Read::kSuperseded;
      if (state == kClosedState) return Read::kClosed;
      return Read::kEmpty;
    }
    if (latest_only && written > *next) {
      *dropped += written - *next;
      *next = written;
    }
    if (written - *next >= h.slot_count) {
      const uint64_t oldest = written - h.slot_count + 1;
      *dropped += oldest - *next;
      *next = oldest;
    }
    const unsigned char* s = slot(*next);
    const auto* sh = reinterpret_cast<const SlotHeader*>(s);
    const uint64_t stamp = sh->stamp.load(std::memory_order_acquire);
    if (stamp % 2 == 1 || stamp > 2 * *next) continue;  // being overwritten: lapped
    if (stamp < 2 * *next) {
      ++*next;  // a number the writer never wrote (a gap): not a loss
      continue;
    }
    const uint64_t length = sh->length.load(std::memory_order_relaxed);
    if (length > h.slot_bytes) continue;
    bytes->assign(reinterpret_cast<const char*>(s + kSlotHeaderBytes), length);
    std::atomic_thread_fence(std::memory_order_acquire);
    if (sh->stamp.load(std::memory_order_relaxed) != stamp) continue;  // lapped while copying
    ++*next;
    return Read::kSample;
  }
}

uint32_t ShmRing::notifyToken() const { return header().notify.load(std::memory_order_seq_cst); }

void ShmRing::wait(uint32_t token, int64_t timeout_ns) const {
  Header& h = header();
  h.sleepers.fetch_add(1, std::memory_order_seq_cst);
  if (h.notify.load(std::memory_order_seq_cst) == token) {
    timespec timeout{static_cast<time_t>(timeout_ns / 1'000'000'000),
                     static_cast<long>(timeout_ns % 1'000'000'000)};
    futex(&h.notify, FUTEX_WAIT, token, &timeout);
  }
  h.sleepers.fetch_sub(1, std::memory_order_seq_cst);
}

void ShmRing::wake() const {
  Header& h = header();
  h.notify.fetch_add(1, std::memory_order_seq_cst);
  futex(&h.notify, FUTEX_WAKE, INT_MAX, nullptr);
}

}  // namespace behaviorlib::channel
