#include "coordinator/durable/journal.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

#include <cerrno>
#include <cstring>

namespace behaviorlib::coordinator {
namespace {

constexpr uint32_t kMaxRecordBytes = 64u << 20;

uint32_t crcOf(std::string_view payload) {
  return static_cast<uint32_t>(
      crc32(0L, reinterpret_cast<const Bytef*>(payload.data()), static_cast<uInt>(payload.size())));
}

void putU32(std::string* out, uint32_t v) {
  for (int i = 0; i < 4; ++i) out->push_back(static_cast<char>((v >> (8 * i)) & 0xff));
}

uint32_t getU32(const char* p) {
  uint32_t v = 0;
  for (int i = 0; i < 4; ++i)
    v |= static_cast<uint32_t>(static_cast<unsigned char>(p[i])) << (8 * i);
  return v;
}

std::string frame(const durable::v1::JournalRecord& record) {
  std::string payload;
  record.SerializeToString(&payload);
  std::string out;
  out.reserve(payload.size() + 8);
  putU32(&out, static_cast<uint32_t>(payload.size()));
  putU32(&out, crcOf(payload));
  out += payload;
  return out;
}

absl::Status errnoError(const std::string& what, const std::string& path) {
  return absl::InternalError(what + " " + path + ": " + std::strerror(errno));
}

}  // namespace

size_t decodeJournal(std::string_view content, const Journal::Replay& replay, uint64_t* records) {
  size_t offset = 0;
  uint64_t count = 0;
  while (content.size() - offset >= 8) {
    const uint32_t length = getU32(content.data() + offset);
    const uint32_t crc = getU32(content.data() + offset + 4);
    if (length > kMaxRecordBytes || content.size() - offset - 8 < length) break;
    const std::string_view payload = content.substr(offset + 8, length);
    durable::v1::JournalRecord record;
    if (crcOf(payload) != crc ||
        !record.ParseFromArray(payload.data(), static_cast<int>(payload.size()))) {
      break;
    }
    replay(record);
    offset += 8 + length;
    ++count;
  }
  if (records != nullptr) *records = count;
  return offset;
}

Journal::Journal(std::string path, int fd, JournalOptions options)
    : path_(std::move(path)), options_(options), fd_(fd) {}

Journal::~Journal() {
  if (fd_ >= 0) ::close(fd_);
}

absl::StatusOr<std::unique_ptr<Journal>> Journal::open(const std::string& path,
                                                       const Replay& replay,
                                                       JournalOptions options) {
  const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (fd < 0) return errnoError("cannot open the journal", path);
  std::unique_ptr<Journal> journal(new Journal(path, fd, options));
  std::string content;
  char buffer[1 << 16];
  for (;;) {
    const ssize_t n = ::read(fd, buffer, sizeof buffer);
    if (n < 0) return errnoError("cannot read the journal", path);
    if (n == 0) break;
    content.append(buffer, static_cast<size_t>(n));
  }
  uint64_t records = 0;
  const size_t offset = decodeJournal(content, replay, &records);
  if (offset < content.size()) {
    journal->truncated_bytes_ = content.size() - offset;
    if (::ftruncate(fd, static_cast<off_t>(offset)) != 0) {
      return errnoError("cannot cut the torn tail of the journal", path);
    }
  }
  if (::lseek(fd, static_cast<off_t>(offset), SEEK_SET) < 0) {
    return errnoError("cannot seek in the journal", path);
  }
  {
    // Not shared yet: the lock only tells the thread-safety analysis so.
    absl::MutexLock lock(&journal->mutex_);
    journal->records_ = records;
    journal->size_ = offset;
  }
  return journal;
}

absl::Status Journal::writeAll(int fd, const std::string& bytes) {
  size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
    if (n < 0) {
      if (errno == EINTR) continue;
      return errnoError("cannot write the journal", path_);
    }
    done += static_cast<size_t>(n);
  }
  return absl::OkStatus();
}

absl::Status Journal::append(const durable::v1::JournalRecord& record) {
  const std::string bytes = frame(record);
  absl::MutexLock lock(&mutex_);
  if (absl::Status s = writeAll(fd_, bytes); !s.ok()) {
    // Do not leave a partial record in front of the next one.
    if (::ftruncate(fd_, static_cast<off_t>(size_)) == 0)
      ::lseek(fd_, static_cast<off_t>(size_), SEEK_SET);
    return s;
  }
  if (options_.fsync_each_append && ::fdatasync(fd_) != 0) {
    return errnoError("cannot sync the journal", path_);
  }
  size_ += bytes.size();
  ++records_;
  if (capturing_) {
    captured_ += bytes;
    ++captured_records_;
  }
  return absl::OkStatus();
}

absl::Status Journal::compact(const std::vector<durable::v1::JournalRecord>& snapshot) {
  std::string bytes;
  for (const auto& record : snapshot) bytes += frame(record);
  absl::MutexLock compaction(&compaction_mutex_);
  absl::MutexLock lock(&mutex_);
  return replaceLocked(bytes, snapshot.size());
}

absl::Status Journal::compactOnline(
    const std::function<std::vector<durable::v1::JournalRecord>()>& snapshot) {
  absl::MutexLock compaction(&compaction_mutex_);
  {
    absl::MutexLock lock(&mutex_);
    capturing_ = true;
    captured_.clear();
    captured_records_ = 0;
  }
  const std::vector<durable::v1::JournalRecord> records = snapshot();
  std::string bytes;
  for (const auto& record : records) bytes += frame(record);
  absl::MutexLock lock(&mutex_);
  bytes += captured_;
  const uint64_t count = records.size() + captured_records_;
  capturing_ = false;
  captured_.clear();
  captured_records_ = 0;
  return replaceLocked(bytes, count);
}

absl::Status Journal::replaceLocked(const std::string& bytes, uint64_t records) {
  const std::string tmp = path_ + ".compact";
  const int fd = ::open(tmp.c_str(), O_RDWR | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) return errnoError("cannot create", tmp);
  absl::Status s = writeAll(fd, bytes);
  if (s.ok() && ::fsync(fd) != 0) s = errnoError("cannot sync", tmp);
  if (s.ok() && ::rename(tmp.c_str(), path_.c_str()) != 0) s = errnoError("cannot replace", path_);
  if (!s.ok()) {
    ::close(fd);
    ::unlink(tmp.c_str());
    return s;
  }
  if (::lseek(fd, 0, SEEK_END) < 0) {
    ::close(fd);
    return errnoError("cannot seek in the journal", path_);
  }
  ::close(fd_);
  fd_ = fd;
  size_ = bytes.size();
  records_ = records;
  return absl::OkStatus();
}

uint64_t Journal::recordCount() const {
  absl::MutexLock lock(&mutex_);
  return records_;
}

uint64_t Journal::sizeBytes() const {
  absl::MutexLock lock(&mutex_);
  return size_;
}

}  // namespace behaviorlib::coordinator
