#include "behaviorlib/configuration.h"

#include <google/protobuf/struct.pb.h>

#include <algorithm>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_replace.h"
#include "absl/strings/str_split.h"
#include "absl/strings/string_view.h"
#include "behaviorlib/errors/status_details.h"
#include "behaviorlib/parameters.h"
#include "behaviorlib/v1/options.pb.h"

namespace behaviorlib::config {
namespace {

namespace pb = google::protobuf;
using FD = pb::FieldDescriptor;

// Flattened messages nest at most this deep; YAML values at most
// kMaxValueDepth (a config file is small; the bound keeps a hostile one from
// exhausting the stack).
constexpr int kMaxFlattenDepth = 8;
constexpr int kMaxValueDepth = 32;

bool flattened(const FD& field) {
  return field.cpp_type() == FD::CPPTYPE_MESSAGE && !field.is_repeated() &&
         field.options().GetExtension(v1::flatten);
}

// The fields that lead from `d` to `key`: the flattened fields passed
// through, then the key's field. False when `d` has no such key.
bool findKey(const pb::Descriptor& d, const std::string& key, std::vector<const FD*>* chain,
             int depth = 0) {
  if (const FD* f = d.FindFieldByName(key); f != nullptr && !flattened(*f)) {
    chain->push_back(f);
    return true;
  }
  if (depth >= kMaxFlattenDepth) return false;
  for (int i = 0; i < d.field_count(); ++i) {
    const FD* f = d.field(i);
    if (!flattened(*f)) continue;
    chain->push_back(f);
    if (findKey(*f->message_type(), key, chain, depth + 1)) return true;
    chain->pop_back();
  }
  return false;
}

void keysOf(const pb::Descriptor& d, std::vector<const FD*>* out, int depth = 0) {
  for (int i = 0; i < d.field_count(); ++i) {
    const FD* f = d.field(i);
    if (!flattened(*f)) {
      out->push_back(f);
    } else if (depth < kMaxFlattenDepth) {
      keysOf(*f->message_type(), out, depth + 1);
    }
  }
}

// Makes every singular message present (flattened or a nested section such
// as navigation_with_lidar's `mapping`), so that its defaults apply even when
// the file sets none of its keys.
void presentSections(pb::Message* m, int depth = 0) {
  const pb::Descriptor& d = *m->GetDescriptor();
  for (int i = 0; i < d.field_count(); ++i) {
    const FD* f = d.field(i);
    if (f->cpp_type() == FD::CPPTYPE_MESSAGE && !f->is_repeated() &&
        f->real_containing_oneof() == nullptr && depth < kMaxFlattenDepth) {
      presentSections(m->GetReflection()->MutableMessage(m, f), depth + 1);
    }
  }
}

std::string located(const Source& source, const YAML::Node& node, absl::string_view message) {
  std::string where = position(node, source.file);
  return absl::StrCat(where, where.empty() ? "" : ": ", source.section,
                      source.section.empty() ? "" : ": ", message);
}

// The parameters' wording, for a configuration file.
std::string asKeys(absl::string_view message) {
  return absl::StrReplaceAll(message, {{"unknown parameter '", "unknown key '"},
                                       {"known parameters:", "known keys:"},
                                       {"parameter '", "key '"},
                                       {"parameters '", "keys '"}});
}

bool isTrue(const std::string& s) { return s == "true" || s == "True" || s == "TRUE"; }
bool isFalse(const std::string& s) { return s == "false" || s == "False" || s == "FALSE"; }

// A YAML value as a protobuf Value, so that params::fromStruct checks types
// exactly as it does for a request's parameters. Plain scalars are read as
// YAML 1.2's core schema reads them (booleans, numbers, else text); a quoted
// scalar is text.
absl::Status toValue(const YAML::Node& node, const Source& source, int depth, pb::Value* out) {
  if (depth > kMaxValueDepth) {
    return absl::InvalidArgumentError(
        located(source, node, absl::StrCat("nested deeper than ", kMaxValueDepth, " levels")));
  }
  switch (node.Type()) {
    case YAML::NodeType::Undefined:
    case YAML::NodeType::Null:
      out->set_null_value(pb::NULL_VALUE);
      return absl::OkStatus();
    case YAML::NodeType::Scalar: {
      const std::string& text = node.Scalar();
      double number = 0;
      if (node.Tag() == "!") {
        out->set_string_value(text);
      } else if (isTrue(text) || isFalse(text)) {
        out->set_bool_value(isTrue(text));
      } else if (absl::SimpleAtod(text, &number)) {
        out->set_number_value(number);
      } else {
        out->set_string_value(text);
      }
      return absl::OkStatus();
    }
    case YAML::NodeType::Sequence: {
      pb::ListValue* list = out->mutable_list_value();
      for (const YAML::Node& item : node) {
        if (absl::Status s = toValue(item, source, depth + 1, list->add_values()); !s.ok()) {
          return s;
        }
      }
      return absl::OkStatus();
    }
    case YAML::NodeType::Map: {
      pb::Struct* fields = out->mutable_struct_value();
      for (const auto& item : node) {
        if (!item.first.IsScalar()) {
          return absl::InvalidArgumentError(located(source, item.first, "a key must be a name"));
        }
        pb::Value value;
        if (absl::Status s = toValue(item.second, source, depth + 1, &value); !s.ok()) return s;
        (*fields->mutable_fields())[item.first.Scalar()] = std::move(value);
      }
      return absl::OkStatus();
    }
  }
  return absl::OkStatus();
}

// The node that a parameter path ("flight.lidar_mount_m[2]") names under the
// section `node` of messages of type `d`; flattened fields are not in the
// file. The deepest node found when the path goes further than the file.
YAML::Node nodeAt(YAML::Node node, const pb::Descriptor* d, absl::string_view path) {
  for (absl::string_view part : absl::StrSplit(path, '.')) {
    absl::string_view name = part.substr(0, part.find('['));
    const FD* field = d != nullptr ? d->FindFieldByName(std::string(name)) : nullptr;
    if (field != nullptr && flattened(*field)) {
      d = field->message_type();
      continue;
    }
    if (!node.IsMap() || !node[std::string(name)]) return node;
    node = node[std::string(name)];
    d = field != nullptr ? field->message_type() : nullptr;
    for (size_t open = part.find('['); open != absl::string_view::npos;
         open = part.find('[', open + 1)) {
      size_t index = 0;
      const size_t close = part.find(']', open);
      if (close == absl::string_view::npos ||
          !absl::SimpleAtoi(part.substr(open + 1, close - open - 1), &index) ||
          !node.IsSequence() || index >= node.size()) {
        return node;
      }
      node = node[index];
    }
  }
  return node;
}

}  // namespace

std::string position(const YAML::Node& node, const std::string& file) {
  const YAML::Mark mark = node.IsDefined() ? node.Mark() : YAML::Mark::null_mark();
  if (mark.is_null()) return file;
  return absl::StrCat(file.empty() ? "<config>" : file, ":", mark.line + 1, ":", mark.column + 1);
}

absl::Status decode(const YAML::Node& node, const Source& source,
                    std::initializer_list<pb::Message*> targets) {
  std::vector<pb::Struct> given(targets.size());
  if (node.IsDefined() && !node.IsNull()) {
    if (!node.IsMap()) {
      return absl::InvalidArgumentError(located(source, node, "must be a map of keys"));
    }
    for (const auto& item : node) {
      if (!item.first.IsScalar()) {
        return absl::InvalidArgumentError(located(source, item.first, "a key must be a name"));
      }
      const std::string key = item.first.Scalar();
      if (std::find(source.skip.begin(), source.skip.end(), key) != source.skip.end()) continue;
      std::vector<const FD*> chain;
      size_t target = 0;
      for (pb::Message* t : targets) {
        if (findKey(*t->GetDescriptor(), key, &chain)) break;
        ++target;
      }
      if (target == targets.size()) {
        std::vector<const FD*> fields;
        for (const pb::Message* t : targets) keysOf(*t->GetDescriptor(), &fields);
        std::vector<std::string> known;
        for (const FD* f : fields) known.push_back(f->name());
        return absl::InvalidArgumentError(
            located(source, item.first,
                    absl::StrCat("unknown key '", key, "'; known keys: ",
                                 known.empty() ? "(none)" : absl::StrJoin(known, ", "))));
      }
      pb::Value value;
      if (absl::Status s = toValue(item.second, source, 1, &value); !s.ok()) return s;
      // The flattened fields become nested objects: fromStruct fills them.
      pb::Struct* at = &given[target];
      for (size_t i = 0; i + 1 < chain.size(); ++i) {
        at = (*at->mutable_fields())[chain[i]->name()].mutable_struct_value();
      }
      if (at->fields().contains(key)) {
        return absl::InvalidArgumentError(
            located(source, item.first, absl::StrCat("key '", key, "' is given twice")));
      }
      (*at->mutable_fields())[key] = std::move(value);
    }
  }
  size_t i = 0;
  for (pb::Message* t : targets) {
    absl::Status s = params::fromStruct(given[i++], t);
    if (s.ok()) presentSections(t);
    if (s.ok()) s = params::applyDefaultsAndValidate(t);
    if (s.ok()) continue;
    if (s.code() != absl::StatusCode::kInvalidArgument) return s;  // a schema bug
    YAML::Node at = node;
    if (auto bad = errors::badRequest(s); bad && bad->field_violations_size() > 0) {
      at = nodeAt(node, t->GetDescriptor(), bad->field_violations(0).field());
    }
    return absl::InvalidArgumentError(located(source, at, asKeys(s.message())));
  }
  return absl::OkStatus();
}

std::string document(std::initializer_list<const pb::Descriptor*> targets,
                     const std::string& indent) {
  std::string out;
  for (const pb::Descriptor* d : targets) {
    std::vector<const FD*> fields;
    keysOf(*d, &fields);
    for (const FD* f : fields) {
      // One schema entry per key: describe() takes a message; the key's
      // own entry is the one whose name is the key.
      pb::RepeatedPtrField<v1::ParameterSchema> schema;
      params::describe(*f->containing_type(), &schema);
      for (const v1::ParameterSchema& entry : schema) {
        if (entry.name() != f->name()) continue;
        absl::StrAppend(&out, indent, entry.name(), " (", entry.type());
        if (!entry.unit().empty()) absl::StrAppend(&out, ", ", entry.unit());
        absl::StrAppend(&out, ")");
        if (entry.has_range()) {
          const v1::Range& r = entry.range();
          absl::StrAppend(&out, " in [", r.has_min() ? absl::StrCat(r.min()) : "-inf", ", ",
                          r.has_max() ? absl::StrCat(r.max()) : "inf", "]");
        }
        if (!entry.default_json().empty())
          absl::StrAppend(&out, ", default ", entry.default_json());
        if (!entry.description().empty()) absl::StrAppend(&out, ": ", entry.description());
        absl::StrAppend(&out, "\n");
      }
    }
  }
  return out;
}

}  // namespace behaviorlib::config
