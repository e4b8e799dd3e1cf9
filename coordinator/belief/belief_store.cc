#include "coordinator/belief/belief_store.h"

#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/time_util.h>

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "coordinator/durable/journal.h"

namespace behaviorlib::coordinator {
namespace {

constexpr const char* kOpen = "${belief.";

std::string valueText(const google::protobuf::Value& value) {
  switch (value.kind_case()) {
    case google::protobuf::Value::kStringValue:
      return value.string_value();
    case google::protobuf::Value::kBoolValue:
      return value.bool_value() ? "true" : "false";
    case google::protobuf::Value::kNullValue:
      return "null";
    default: {
      std::string json;
      (void)google::protobuf::util::MessageToJsonString(value, &json);
      return json;
    }
  }
}

}  // namespace

BeliefStore::BeliefStore(Journal* journal, BeliefLimits limits)
    : journal_(journal), limits_(limits) {}

void BeliefStore::account(const v1::Belief* before, const v1::Belief* now) {
  if (before != nullptr) {
    if (before->deleted()) {
      tombstones_.erase({before->version(), before->key()});
    } else {
      --live_count_;
      live_bytes_ -= before->value().ByteSizeLong();
    }
  }
  if (now != nullptr) {
    if (now->deleted()) {
      tombstones_.insert({now->version(), now->key()});
    } else {
      ++live_count_;
      live_bytes_ += now->value().ByteSizeLong();
    }
  }
}

void BeliefStore::forgetOldTombstones() {
  while (tombstones_.size() > limits_.max_tombstones) {
    const auto oldest = tombstones_.begin();
    beliefs_.erase(oldest->second);
    tombstones_.erase(oldest);
  }
}

absl::Status BeliefStore::checkKey(const std::string& key) {
  auto bad = [&](const std::string& why) {
    return absl::InvalidArgumentError(
        "belief key '" + key + "' " + why +
        " (letters, digits, '_', '-', '.', segments separated by '/')");
  };
  if (key.empty()) return bad("is empty");
  if (key.size() > 256) return bad("is longer than 256 characters");
  if (key.front() == '/' || key.back() == '/' || key.find("//") != std::string::npos) {
    return bad("has an empty segment");
  }
  for (char c : key) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
                    c == '_' || c == '-' || c == '.' || c == '/';
    if (!ok) return bad(std::string("has the character '") + c + "'");
  }
  return absl::OkStatus();
}

absl::StatusOr<std::vector<std::string>> BeliefStore::bindingsIn(const std::string& text) {
  std::vector<std::string> keys;
  for (size_t at = text.find(kOpen); at != std::string::npos; at = text.find(kOpen, at)) {
    const size_t start = at + std::char_traits<char>::length(kOpen);
    const size_t end = text.find('}', start);
    if (end == std::string::npos) {
      return absl::InvalidArgumentError("unterminated binding in '" + text +
                                        "' (expected ${belief.<key>})");
    }
    const std::string key = text.substr(start, end - start);
    if (absl::Status s = checkKey(key); !s.ok()) {
      return absl::InvalidArgumentError("binding in '" + text + "': " + std::string(s.message()));
    }
    keys.push_back(key);
    at = end + 1;
  }
  return keys;
}

void BeliefStore::restore(const v1::Belief& belief) {
  absl::MutexLock lock(&mutex_);
  auto it = beliefs_.find(belief.key());
  account(it == beliefs_.end() ? nullptr : &it->second, &belief);
  beliefs_[belief.key()] = belief;
  version_ = std::max(version_, belief.version());
  forgetOldTombstones();
}

absl::StatusOr<v1::Belief> BeliefStore::write(const std::string& key,
                                              const google::protobuf::Value& value,
                                              const std::string& writer, const std::string& type,
                                              const std::string& authenticated_writer) {
  if (absl::Status s = checkKey(key); !s.ok()) return s;
  v1::Belief belief;
  belief.set_key(key);
  *belief.mutable_value() = value;
  belief.set_type(type);
  belief.set_writer(writer);
  belief.set_authenticated_writer(authenticated_writer);
  *belief.mutable_update_time() = google::protobuf::util::TimeUtil::GetCurrentTime();
  const size_t bytes = value.ByteSizeLong();
  if (bytes > limits_.max_value_bytes) {
    return absl::ResourceExhaustedError(absl::StrCat("belief '", key, "': its value is ", bytes,
                                                     " bytes, more than the ",
                                                     limits_.max_value_bytes, " allowed"));
  }
  {
    absl::MutexLock lock(&mutex_);
    auto existing = beliefs_.find(key);
    const bool replaces = existing != beliefs_.end() && !existing->second.deleted();
    if (!replaces && live_count_ >= limits_.max_beliefs) {
      return absl::ResourceExhaustedError(absl::StrCat("belief memory holds ", live_count_,
                                                       " beliefs, the most allowed; "
                                                       "delete some before writing '",
                                                       key, "'"));
    }
    const size_t freed = replaces ? existing->second.value().ByteSizeLong() : 0;
    if (live_bytes_ - freed + bytes > limits_.max_total_bytes) {
      return absl::ResourceExhaustedError(
          absl::StrCat("belief memory holds ", live_bytes_, " bytes of values; writing '", key,
                       "' would pass the ", limits_.max_total_bytes, " allowed"));
    }
    belief.set_version(version_ + 1);
    if (journal_ != nullptr) {
      durable::v1::JournalRecord record;
      *record.mutable_belief() = belief;
      if (absl::Status s = journal_->append(record); !s.ok()) return s;
    }
    version_ = belief.version();
    account(existing == beliefs_.end() ? nullptr : &existing->second, &belief);
    beliefs_[key] = belief;
  }  // a waitForChanges' Await sees the new version_ at this unlock
  return belief;
}

absl::StatusOr<v1::Belief> BeliefStore::writeMessage(const std::string& key,
                                                     const google::protobuf::Message& message,
                                                     const std::string& writer) {
  std::string json;
  google::protobuf::util::JsonPrintOptions options;
  options.preserve_proto_field_names = true;  // position_m, as in parameters
  if (!google::protobuf::util::MessageToJsonString(message, &json, options).ok()) {
    return absl::InvalidArgumentError("cannot encode " + message.GetTypeName() + " as JSON");
  }
  google::protobuf::Value value;
  if (!google::protobuf::util::JsonStringToMessage(json, &value).ok()) {
    return absl::InternalError("cannot decode the JSON form of " + message.GetTypeName());
  }
  return write(key, value, writer, message.GetTypeName());
}

absl::Status BeliefStore::erase(const std::string& key, const std::string& writer,
                                const std::string& authenticated_writer) {
  {
    absl::MutexLock lock(&mutex_);
    auto it = beliefs_.find(key);
    if (it == beliefs_.end() || it->second.deleted()) {
      return absl::NotFoundError("no belief '" + key + "' in memory");
    }
    v1::Belief tombstone;
    tombstone.set_key(key);
    tombstone.set_writer(writer);
    tombstone.set_authenticated_writer(authenticated_writer);
    tombstone.set_deleted(true);
    tombstone.set_version(version_ + 1);
    *tombstone.mutable_update_time() = google::protobuf::util::TimeUtil::GetCurrentTime();
    if (journal_ != nullptr) {
      durable::v1::JournalRecord record;
      *record.mutable_belief() = tombstone;
      if (absl::Status s = journal_->append(record); !s.ok()) return s;
    }
    version_ = tombstone.version();
    account(&it->second, &tombstone);
    it->second = tombstone;
    forgetOldTombstones();
  }
  return absl::OkStatus();
}

std::optional<v1::Belief> BeliefStore::get(const std::string& key) const {
  absl::MutexLock lock(&mutex_);
  auto it = beliefs_.find(key);
  if (it == beliefs_.end() || it->second.deleted()) return std::nullopt;
  return it->second;
}

std::vector<v1::Belief> BeliefStore::list(const std::string& prefix) const {
  absl::MutexLock lock(&mutex_);
  std::vector<v1::Belief> out;
  for (auto it = beliefs_.lower_bound(prefix); it != beliefs_.end(); ++it) {
    if (it->first.compare(0, prefix.size(), prefix) != 0) break;
    if (!it->second.deleted()) out.push_back(it->second);
  }
  return out;
}

uint64_t BeliefStore::version() const {
  absl::MutexLock lock(&mutex_);
  return version_;
}

std::vector<v1::Belief> BeliefStore::waitForChanges(uint64_t since_version,
                                                    const std::string& prefix,
                                                    std::chrono::milliseconds timeout) const {
  absl::MutexLock lock(&mutex_);
  auto collect = [&]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    std::vector<v1::Belief> out;
    for (const auto& [key, belief] : beliefs_) {
      if (belief.version() > since_version && key.compare(0, prefix.size(), prefix) == 0) {
        out.push_back(belief);
      }
    }
    std::sort(out.begin(), out.end(),
              [](const v1::Belief& a, const v1::Belief& b) { return a.version() < b.version(); });
    return out;
  };
  std::vector<v1::Belief> out = collect();
  const absl::Time deadline = absl::Now() + absl::FromChrono(timeout);
  while (out.empty() && !woken_) {
    // Until any write (a new version_) or wakeAll, then look again.
    const uint64_t seen = version_;
    const auto changed = [this, seen]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
      return woken_ || version_ != seen;
    };
    if (!mutex_.AwaitWithDeadline(absl::Condition(&changed), deadline)) break;
    out = collect();
  }
  return out;
}

void BeliefStore::wakeAll() {
  {
    absl::MutexLock lock(&mutex_);
    woken_ = true;
  }
}

absl::StatusOr<google::protobuf::Value> BeliefStore::resolveValue(
    const google::protobuf::Value& value) const {
  google::protobuf::Value out = value;
  if (value.has_string_value()) {
    const std::string& text = value.string_value();
    auto keys = bindingsIn(text);
    if (!keys.ok()) return keys.status();
    if (keys->empty()) return out;
    absl::MutexLock lock(&mutex_);
    auto lookup = [&](const std::string& key) ABSL_EXCLUSIVE_LOCKS_REQUIRED(
                      mutex_) -> absl::StatusOr<google::protobuf::Value> {
      auto it = beliefs_.find(key);
      if (it == beliefs_.end() || it->second.deleted()) {
        return absl::FailedPreconditionError("belief '" + key + "' is not in memory (bound by '" +
                                             text + "')");
      }
      return it->second.value();
    };
    if (keys->size() == 1 && text == std::string(kOpen) + keys->front() + "}") {
      return lookup(keys->front());
    }
    std::string result = text;
    for (const auto& key : *keys) {
      auto v = lookup(key);
      if (!v.ok()) return v.status();
      const std::string binding = std::string(kOpen) + key + "}";
      result.replace(result.find(binding), binding.size(), valueText(*v));
    }
    out.set_string_value(result);
  } else if (value.has_list_value()) {
    auto* list = out.mutable_list_value();
    for (int i = 0; i < list->values_size(); ++i) {
      auto v = resolveValue(value.list_value().values(i));
      if (!v.ok()) return v.status();
      *list->mutable_values(i) = *v;
    }
  } else if (value.has_struct_value()) {
    auto s = resolve(value.struct_value());
    if (!s.ok()) return s.status();
    *out.mutable_struct_value() = *s;
  }
  return out;
}

absl::StatusOr<google::protobuf::Struct> BeliefStore::resolve(
    const google::protobuf::Struct& parameters) const {
  google::protobuf::Struct out;
  for (const auto& [key, value] : parameters.fields()) {
    auto v = resolveValue(value);
    if (!v.ok()) return v.status();
    (*out.mutable_fields())[key] = *v;
  }
  return out;
}

std::vector<v1::Belief> BeliefStore::snapshot() const {
  absl::MutexLock lock(&mutex_);
  std::vector<v1::Belief> out;
  for (const auto& [key, belief] : beliefs_) out.push_back(belief);
  return out;
}

}  // namespace behaviorlib::coordinator
