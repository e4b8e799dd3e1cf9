#include "formats/mcap/mcap.h"

#include <zlib.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"

namespace behaviorlib::recorder::mcap {

namespace {

constexpr char kMagic[] = "\x89MCAP0\r\n";
constexpr size_t kMagicBytes = 8;

enum Opcode : uint8_t {
  kHeader = 0x01,
  kFooter = 0x02,
  kSchema = 0x03,
  kChannel = 0x04,
  kMessage = 0x05,
  kChunk = 0x06,
  kStatistics = 0x0B,
  kSummaryOffset = 0x0E,
  kDataEnd = 0x0F,
};

uint32_t crc32Update(uint32_t crc, std::string_view bytes) {
  return static_cast<uint32_t>(
      ::crc32(crc, reinterpret_cast<const Bytef*>(bytes.data()), static_cast<uInt>(bytes.size())));
}

// Little-endian encoding of the spec's field types.
template <typename T>
void putInt(std::string& out, T value) {
  for (size_t i = 0; i < sizeof(T); ++i) {
    out.push_back(static_cast<char>((static_cast<uint64_t>(value) >> (8 * i)) & 0xff));
  }
}

void putString(std::string& out, std::string_view value) {
  putInt<uint32_t>(out, static_cast<uint32_t>(value.size()));
  out.append(value);
}

std::string record(uint8_t opcode, const std::string& content) {
  std::string out;
  out.reserve(content.size() + 9);
  out.push_back(static_cast<char>(opcode));
  putInt<uint64_t>(out, content.size());
  out.append(content);
  return out;
}

std::string schemaContent(const Schema& schema) {
  std::string out;
  putInt<uint16_t>(out, schema.id);
  putString(out, schema.name);
  putString(out, schema.encoding);
  putString(out, schema.data);
  return out;
}

std::string channelContent(const Channel& channel) {
  std::string out;
  putInt<uint16_t>(out, channel.id);
  putInt<uint16_t>(out, channel.schema_id);
  putString(out, channel.topic);
  putString(out, channel.message_encoding);
  std::string map;
  for (const auto& [key, value] : channel.metadata) {
    putString(map, key);
    putString(map, value);
  }
  putString(out, map);
  return out;
}

// Reads fields of one record's content; any read past its end makes ok()
// false.
class Fields {
 public:
  explicit Fields(std::string_view content) : rest_(content) {}

  template <typename T>
  T integer() {
    if (rest_.size() < sizeof(T)) return fail<T>();
    uint64_t value = 0;
    for (size_t i = 0; i < sizeof(T); ++i) {
      value |= static_cast<uint64_t>(static_cast<uint8_t>(rest_[i])) << (8 * i);
    }
    rest_.remove_prefix(sizeof(T));
    return static_cast<T>(value);
  }
  std::string_view bytes(uint64_t size) {
    if (rest_.size() < size) return fail<std::string_view>();
    std::string_view out = rest_.substr(0, size);
    rest_.remove_prefix(size);
    return out;
  }
  std::string string() { return std::string(bytes(integer<uint32_t>())); }
  std::map<std::string, std::string> stringMap() {
    Fields map(bytes(integer<uint32_t>()));
    std::map<std::string, std::string> out;
    while (ok_ && map.ok_ && !map.rest_.empty()) {
      std::string key = map.string();
      out[key] = map.string();
    }
    if (!map.ok_) ok_ = false;
    return out;
  }
  std::string_view rest() const { return rest_; }
  bool ok() const { return ok_; }

 private:
  template <typename T>
  T fail() {
    ok_ = false;
    rest_ = {};
    return T{};
  }
  std::string_view rest_;
  bool ok_ = true;
};

struct FileCloser {
  void operator()(std::FILE* file) const { std::fclose(file); }
};

class Scanner {
 public:
  // `path` names the file in errors; `file` is read from its start.
  Scanner(const std::string& path, std::FILE* file, const ReadLimits& limits,
          const std::function<bool(const ScanSummary&, const Message&)>& on_message)
      : path_(path), limits_(limits), on_message_(on_message), file_(file) {}

  absl::StatusOr<ScanSummary> run() {
    char magic[kMagicBytes];
    const size_t got = std::fread(magic, 1, kMagicBytes, file_);
    if (std::memcmp(magic, kMagic, got) != 0) {
      return absl::InvalidArgumentError(absl::StrCat(path_, " is not an MCAP file"));
    }
    // Shorter than the magic, but its start: a recording that has just
    // begun, with nothing in it yet.
    if (got < kMagicBytes) return std::move(summary_);
    offset_ = kMagicBytes;
    bool first = true;
    while (true) {
      uint8_t opcode = 0;
      std::string content;
      const uint64_t at = offset_;
      bool whole = false;
      if (absl::Status read = next(&opcode, &content, &whole); !read.ok()) return read;
      if (!whole) break;  // Ended early: what came before is read.
      if (first && opcode != kHeader) return malformed(at, "the first record is not a Header");
      first = false;
      if (opcode == kFooter) {
        char end[kMagicBytes];
        summary_.complete = std::fread(end, 1, kMagicBytes, file_) == kMagicBytes &&
                            std::memcmp(end, kMagic, kMagicBytes) == 0;
        break;
      }
      if (absl::Status handled = handle(opcode, content, at); !handled.ok()) return handled;
      if (summary_.stopped) break;
    }
    return std::move(summary_);
  }

 private:
  // The next record; *whole is false at the end of the file or when the
  // file ends inside the record.
  absl::Status next(uint8_t* opcode, std::string* content, bool* whole) {
    char head[9];
    const size_t got = std::fread(head, 1, sizeof head, file_);
    if (got < sizeof head) return absl::OkStatus();
    Fields fields(std::string_view(head + 1, 8));
    *opcode = static_cast<uint8_t>(head[0]);
    const uint64_t length = fields.integer<uint64_t>();
    if (length > limits_.max_record_bytes) {
      return malformed(offset_, absl::StrCat("a record of ", length, " bytes is over the limit of ",
                                             limits_.max_record_bytes));
    }
    if (offset_ + sizeof head + length > limits_.max_file_bytes) {
      return absl::ResourceExhaustedError(
          absl::StrCat(path_, " is larger than the limit of ", limits_.max_file_bytes, " bytes"));
    }
    content->resize(length);
    if (length > 0 && std::fread(content->data(), 1, length, file_) != length) {
      return absl::OkStatus();
    }
    offset_ += sizeof head + length;
    *whole = true;
    return absl::OkStatus();
  }

  absl::Status malformed(uint64_t at, const std::string& why) const {
    return absl::InvalidArgumentError(
        absl::StrCat(path_, ": malformed MCAP record at byte ", at, ": ", why));
  }

  absl::Status handle(uint8_t opcode, std::string_view content, uint64_t at) {
    Fields fields(content);
    switch (opcode) {
      case kHeader:
        summary_.profile = fields.string();
        summary_.library = fields.string();
        break;
      case kSchema: {
        Schema schema;
        schema.id = fields.integer<uint16_t>();
        schema.name = fields.string();
        schema.encoding = fields.string();
        schema.data = std::string(fields.bytes(fields.integer<uint32_t>()));
        if (!fields.ok()) break;
        if (schema.id == 0) break;  // Id 0 is no schema (the spec's rule).
        if (summary_.schemas.count(schema.id) == 0 &&
            summary_.schemas.size() >= limits_.max_schemas) {
          return malformed(at, absl::StrCat("more than ", limits_.max_schemas, " schemas"));
        }
        summary_.schemas[schema.id] = std::move(schema);
        break;
      }
      case kChannel: {
        Channel channel;
        channel.id = fields.integer<uint16_t>();
        channel.schema_id = fields.integer<uint16_t>();
        channel.topic = fields.string();
        channel.message_encoding = fields.string();
        channel.metadata = fields.stringMap();
        if (!fields.ok()) break;
        if (channel.schema_id != 0 && summary_.schemas.count(channel.schema_id) == 0) {
          return malformed(at, absl::StrCat("channel ", channel.id, " names schema ",
                                            channel.schema_id, ", which came before it"));
        }
        if (summary_.channels.count(channel.id) == 0 &&
            summary_.channels.size() >= limits_.max_channels) {
          return malformed(at, absl::StrCat("more than ", limits_.max_channels, " channels"));
        }
        summary_.channels[channel.id] = std::move(channel);
        break;
      }
      case kMessage: {
        Message message;
        message.channel_id = fields.integer<uint16_t>();
        message.sequence = fields.integer<uint32_t>();
        message.log_time_ns = fields.integer<uint64_t>();
        message.publish_time_ns = fields.integer<uint64_t>();
        if (!fields.ok()) break;
        message.data = std::string(fields.rest());
        if (summary_.channels.count(message.channel_id) == 0) {
          return malformed(at, absl::StrCat("a message on channel ", message.channel_id,
                                            ", which came before it"));
        }
        ++summary_.message_count;
        if (!on_message_(summary_, message)) summary_.stopped = true;
        break;
      }
      case kChunk: {
        fields.integer<uint64_t>();  // message_start_time
        fields.integer<uint64_t>();  // message_end_time
        const uint64_t uncompressed_size = fields.integer<uint64_t>();
        fields.integer<uint32_t>();  // uncompressed_crc
        const std::string compression = fields.string();
        const std::string_view records = fields.bytes(fields.integer<uint64_t>());
        if (!fields.ok()) break;
        if (!compression.empty()) {
          return absl::FailedPreconditionError(
              absl::StrCat(path_, ": the chunk at byte ", at, " is compressed with ", compression,
                           ", which this reader does not read (record without compression)"));
        }
        if (uncompressed_size != records.size()) {
          return malformed(at, "the chunk's size does not match its records");
        }
        return inner(records, at);
      }
      default:
        return absl::OkStatus();  // Indexes, attachments, metadata, summary.
    }
    if (!fields.ok()) return malformed(at, "the record is shorter than its fields");
    return absl::OkStatus();
  }

  // The records of an uncompressed chunk.
  absl::Status inner(std::string_view records, uint64_t chunk_at) {
    Fields fields(records);
    while (fields.ok() && !fields.rest().empty() && !summary_.stopped) {
      const uint8_t opcode = fields.integer<uint8_t>();
      const std::string_view content = fields.bytes(fields.integer<uint64_t>());
      if (!fields.ok()) break;
      if (opcode == kChunk || opcode == kHeader || opcode == kFooter) {
        return malformed(chunk_at, "a chunk holds a record a chunk may not hold");
      }
      if (absl::Status handled = handle(opcode, content, chunk_at); !handled.ok()) return handled;
    }
    if (!fields.ok()) return malformed(chunk_at, "the chunk's records are cut short");
    return absl::OkStatus();
  }

  const std::string& path_;
  const ReadLimits& limits_;
  const std::function<bool(const ScanSummary&, const Message&)>& on_message_;
  std::FILE* const file_;
  uint64_t offset_ = 0;
  ScanSummary summary_;
};

}  // namespace

Writer::Writer(std::FILE* file, std::string path) : file_(file), path_(std::move(path)) {}

Writer::~Writer() {
  if (!closed_) close().IgnoreError();
}

absl::StatusOr<std::unique_ptr<Writer>> Writer::create(const std::string& path,
                                                       const std::string& profile,
                                                       const std::string& library) {
  std::FILE* file = std::fopen(path.c_str(), "wb");
  if (file == nullptr) {
    return absl::PermissionDeniedError(
        absl::StrCat("cannot create ", path, ": ", std::strerror(errno)));
  }
  std::unique_ptr<Writer> writer(new Writer(file, path));
  std::string header;
  putString(header, profile);
  putString(header, library);
  // The data section's CRC starts with the magic (as @mcap/core's writer has it).
  const std::string magic(kMagic, kMagicBytes);
  writer->data_crc_ = crc32Update(0, magic);
  if (absl::Status put = writer->put(magic); !put.ok()) return put;
  if (absl::Status put = writer->putRecord(kHeader, header, true); !put.ok()) return put;
  // A reader that opens the file at once finds an MCAP file.
  if (absl::Status flushed = writer->flush(); !flushed.ok()) return flushed;
  return writer;
}

absl::Status Writer::put(const std::string& bytes) {
  if (std::fwrite(bytes.data(), 1, bytes.size(), file_) != bytes.size()) {
    return absl::UnavailableError(absl::StrCat("cannot write ", path_, ": ", std::strerror(errno)));
  }
  offset_ += bytes.size();
  return absl::OkStatus();
}

absl::Status Writer::putRecord(uint8_t opcode, const std::string& content, bool data_section) {
  const std::string bytes = record(opcode, content);
  if (data_section) data_crc_ = crc32Update(data_crc_, bytes);
  return put(bytes);
}

absl::StatusOr<uint16_t> Writer::addSchema(const std::string& name, const std::string& encoding,
                                           const std::string& data) {
  if (closed_) return absl::FailedPreconditionError("the recording is closed");
  auto it = schemas_.find({name, encoding});
  if (it != schemas_.end()) return it->second.id;
  if (schemas_.size() >= 0xfffe) return absl::ResourceExhaustedError("too many schemas");
  Schema schema{static_cast<uint16_t>(schemas_.size() + 1), name, encoding, data};
  if (absl::Status put = putRecord(kSchema, schemaContent(schema), true); !put.ok()) return put;
  schemas_.emplace(std::make_pair(name, encoding), schema);
  return schema.id;
}

absl::StatusOr<uint16_t> Writer::addChannel(uint16_t schema_id, const std::string& topic,
                                            const std::string& message_encoding,
                                            const std::map<std::string, std::string>& metadata) {
  if (closed_) return absl::FailedPreconditionError("the recording is closed");
  auto it = channels_.find({topic, schema_id});
  if (it != channels_.end()) return it->second.id;
  if (channels_.size() >= 0xfffe) return absl::ResourceExhaustedError("too many channels");
  Channel channel{static_cast<uint16_t>(channels_.size() + 1), schema_id, topic, message_encoding,
                  metadata};
  if (absl::Status put = putRecord(kChannel, channelContent(channel), true); !put.ok()) return put;
  channels_.emplace(std::make_pair(topic, schema_id), channel);
  return channel.id;
}

absl::Status Writer::write(uint16_t channel_id, uint64_t log_time_ns, uint64_t publish_time_ns,
                           const std::string& data) {
  if (closed_) return absl::FailedPreconditionError("the recording is closed");
  if (channel_id == 0 || channel_id > channels_.size()) {
    return absl::InvalidArgumentError(absl::StrCat("no channel ", channel_id));
  }
  std::string content;
  content.reserve(data.size() + 22);
  putInt<uint16_t>(content, channel_id);
  putInt<uint32_t>(content, sequences_[channel_id]++);
  putInt<uint64_t>(content, log_time_ns);
  putInt<uint64_t>(content, publish_time_ns);
  content.append(data);
  if (absl::Status put = putRecord(kMessage, content, true); !put.ok()) return put;
  if (message_count_ == 0 || log_time_ns < first_time_ns_) first_time_ns_ = log_time_ns;
  last_time_ns_ = std::max(last_time_ns_, log_time_ns);
  ++message_count_;
  ++channel_counts_[channel_id];
  return absl::OkStatus();
}

absl::Status Writer::flush() {
  if (closed_) return absl::OkStatus();
  if (std::fflush(file_) != 0) {
    return absl::UnavailableError(absl::StrCat("cannot write ", path_, ": ", std::strerror(errno)));
  }
  return absl::OkStatus();
}

absl::Status Writer::close() {
  if (closed_) return absl::OkStatus();
  closed_ = true;
  absl::Status status = [&]() -> absl::Status {
    std::string data_end;
    putInt<uint32_t>(data_end, data_crc_);
    if (absl::Status put = putRecord(kDataEnd, data_end, false); !put.ok()) return put;

    // The summary: every schema and channel again, then the statistics; its
    // CRC runs from here through the Footer's summary_offset_start.
    const uint64_t summary_start = offset_;
    std::string summary;
    struct Group {
      uint8_t opcode;
      uint64_t start;
      uint64_t length;
    };
    std::vector<Group> groups;
    auto group = [&](uint8_t opcode, const std::vector<std::string>& contents) {
      if (contents.empty()) return;
      Group g{opcode, summary_start + summary.size(), 0};
      for (const auto& content : contents) summary += record(opcode, content);
      g.length = summary_start + summary.size() - g.start;
      groups.push_back(g);
    };
    std::vector<std::pair<uint16_t, std::string>> schemas;
    for (const auto& [key, schema] : schemas_)
      schemas.emplace_back(schema.id, schemaContent(schema));
    std::sort(schemas.begin(), schemas.end());
    std::vector<std::string> contents;
    for (auto& [id, content] : schemas) contents.push_back(std::move(content));
    group(kSchema, contents);
    std::vector<std::pair<uint16_t, std::string>> channels;
    for (const auto& [key, channel] : channels_) {
      channels.emplace_back(channel.id, channelContent(channel));
    }
    std::sort(channels.begin(), channels.end());
    contents.clear();
    for (auto& [id, content] : channels) contents.push_back(std::move(content));
    group(kChannel, contents);
    std::string statistics;
    putInt<uint64_t>(statistics, message_count_);
    putInt<uint16_t>(statistics, static_cast<uint16_t>(schemas_.size()));
    putInt<uint32_t>(statistics, static_cast<uint32_t>(channels_.size()));
    putInt<uint32_t>(statistics, 0);  // attachments
    putInt<uint32_t>(statistics, 0);  // metadata
    putInt<uint32_t>(statistics, 0);  // chunks
    putInt<uint64_t>(statistics, first_time_ns_);
    putInt<uint64_t>(statistics, last_time_ns_);
    std::string counts;
    for (const auto& [id, count] : channel_counts_) {
      putInt<uint16_t>(counts, id);
      putInt<uint64_t>(counts, count);
    }
    putString(statistics, counts);
    group(kStatistics, {statistics});

    const uint64_t offsets_start = summary_start + summary.size();
    for (const auto& g : groups) {
      std::string content;
      putInt<uint8_t>(content, g.opcode);
      putInt<uint64_t>(content, g.start);
      putInt<uint64_t>(content, g.length);
      summary += record(kSummaryOffset, content);
    }
    std::string footer;
    putInt<uint64_t>(footer, summary_start);
    putInt<uint64_t>(footer, offsets_start);
    std::string footer_head;
    footer_head.push_back(static_cast<char>(kFooter));
    putInt<uint64_t>(footer_head, 20);
    uint32_t summary_crc = crc32Update(0, summary);
    summary_crc = crc32Update(summary_crc, footer_head + footer);
    putInt<uint32_t>(footer, summary_crc);
    if (absl::Status put = this->put(summary); !put.ok()) return put;
    if (absl::Status put = putRecord(kFooter, footer, false); !put.ok()) return put;
    return this->put(std::string(kMagic, kMagicBytes));
  }();
  if (std::fclose(file_) != 0 && status.ok()) {
    status =
        absl::UnavailableError(absl::StrCat("cannot write ", path_, ": ", std::strerror(errno)));
  }
  file_ = nullptr;
  return status;
}

absl::StatusOr<ScanSummary> scan(
    const std::string& path, const ReadLimits& limits,
    const std::function<bool(const ScanSummary&, const Message&)>& on_message) {
  std::unique_ptr<std::FILE, FileCloser> file(std::fopen(path.c_str(), "rb"));
  if (!file) {
    return absl::NotFoundError(absl::StrCat("cannot open ", path, ": ", std::strerror(errno)));
  }
  return Scanner(path, file.get(), limits, on_message).run();
}

absl::StatusOr<ScanSummary> scanBytes(
    std::string_view bytes, const ReadLimits& limits,
    const std::function<bool(const ScanSummary&, const Message&)>& on_message) {
  if (bytes.empty()) return ScanSummary{};  // fmemopen takes no empty buffer.
  std::unique_ptr<std::FILE, FileCloser> file(
      fmemopen(const_cast<char*>(bytes.data()), bytes.size(), "rb"));
  if (!file) return absl::InternalError(absl::StrCat("fmemopen: ", std::strerror(errno)));
  return Scanner("the recording", file.get(), limits, on_message).run();
}

}  // namespace behaviorlib::recorder::mcap
