#pragma once

// The part of MCAP (https://mcap.dev/spec, major version 0) the flight
// recorder writes and reads (decision 36): a file of Schema, Channel and
// Message records in an unchunked data section, then DataEnd with the data
// section's CRC-32, a summary section (every Schema and Channel again and a
// Statistics record) with its Summary Offset records, the Footer and the
// closing magic. Foxglove, the `mcap` CLI and @mcap/core read such a file;
// tests/integration/mcap_conformance.mjs checks ours with @mcap/core.
//
// The reader takes what the writer writes, and also files of other writers
// whose chunks are uncompressed; it skips records it does not use (message
// indexes, attachments, metadata). A file that ends early (a recorder that
// was killed) reads up to its last whole record and says it is incomplete.

#include <cstdint>
#include <cstdio>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace behaviorlib::recorder::mcap {

struct Schema {
  uint16_t id = 0;
  std::string name;
  /// "protobuf": data is a serialized google.protobuf.FileDescriptorSet.
  std::string encoding;
  std::string data;
};

struct Channel {
  uint16_t id = 0;
  uint16_t schema_id = 0;
  std::string topic;
  std::string message_encoding;
  std::map<std::string, std::string> metadata;
};

struct Message {
  uint16_t channel_id = 0;
  uint32_t sequence = 0;
  /// Nanoseconds since the Unix epoch.
  uint64_t log_time_ns = 0;
  uint64_t publish_time_ns = 0;
  std::string data;
};

class Writer {
 public:
  /// Creates (truncates) `path` and writes the magic and the Header.
  static absl::StatusOr<std::unique_ptr<Writer>> create(const std::string& path,
                                                        const std::string& profile,
                                                        const std::string& library);
  ~Writer();
  Writer(const Writer&) = delete;
  Writer& operator=(const Writer&) = delete;

  /// The id of the schema (name, encoding), written the first time.
  absl::StatusOr<uint16_t> addSchema(const std::string& name, const std::string& encoding,
                                     const std::string& data);
  /// The id of the channel (topic, schema), written the first time.
  absl::StatusOr<uint16_t> addChannel(uint16_t schema_id, const std::string& topic,
                                      const std::string& message_encoding,
                                      const std::map<std::string, std::string>& metadata = {});
  absl::Status write(uint16_t channel_id, uint64_t log_time_ns, uint64_t publish_time_ns,
                     const std::string& data);
  /// Hands what is written to the operating system, so that a killed
  /// recorder loses at most what came after.
  absl::Status flush();
  /// Writes DataEnd, the summary and the Footer, and closes the file.
  absl::Status close();

  uint64_t messageCount() const { return message_count_; }
  uint64_t bytesWritten() const { return offset_; }

 private:
  Writer(std::FILE* file, std::string path);
  absl::Status put(const std::string& bytes);
  absl::Status putRecord(uint8_t opcode, const std::string& content, bool data_section);

  std::FILE* file_;
  const std::string path_;
  uint64_t offset_ = 0;
  uint32_t data_crc_ = 0;
  bool closed_ = false;
  std::map<std::pair<std::string, std::string>, Schema> schemas_;
  std::map<std::pair<std::string, uint16_t>, Channel> channels_;
  std::map<uint16_t, uint32_t> sequences_;
  std::map<uint16_t, uint64_t> channel_counts_;
  uint64_t message_count_ = 0;
  uint64_t first_time_ns_ = 0;
  uint64_t last_time_ns_ = 0;
};

struct ReadLimits {
  /// Largest file read.
  uint64_t max_file_bytes = uint64_t{8} << 30;
  /// Largest record (and largest uncompressed chunk).
  uint64_t max_record_bytes = uint64_t{64} << 20;
  /// Schemas and channels kept.
  size_t max_schemas = 4096;
  size_t max_channels = 4096;
};

/// What a scan found besides the messages.
struct ScanSummary {
  std::string profile;
  std::string library;
  std::map<uint16_t, Schema> schemas;
  std::map<uint16_t, Channel> channels;
  uint64_t message_count = 0;
  /// False when the file ended before its Footer (a recorder killed).
  bool complete = false;
  /// True when the scan was stopped by the visitor.
  bool stopped = false;
};

/// Reads `path` from the start and hands each message to `on_message`, in
/// file order, with the schemas and channels known so far; the visitor
/// returns false to stop. INVALID_ARGUMENT names the file and the offset of
/// a malformed record; FAILED_PRECONDITION a compressed chunk (not read).
absl::StatusOr<ScanSummary> scan(
    const std::string& path, const ReadLimits& limits,
    const std::function<bool(const ScanSummary&, const Message&)>& on_message);

/// scan() of a file's bytes in memory (the fuzz target's way in).
absl::StatusOr<ScanSummary> scanBytes(
    std::string_view bytes, const ReadLimits& limits,
    const std::function<bool(const ScanSummary&, const Message&)>& on_message);

}  // namespace behaviorlib::recorder::mcap
