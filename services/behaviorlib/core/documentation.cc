#include "behaviorlib/documentation.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/descriptor.pb.h>

#include <memory>
#include <sstream>

#include "behaviorlib/embedded_descriptors.h"

namespace behaviorlib {
namespace {

// A pool of our own files with their source info, built once.
const google::protobuf::DescriptorPool& documentedPool() {
  static const auto* pool = [] {
    auto* p = new google::protobuf::DescriptorPool();
    google::protobuf::FileDescriptorSet set;
    const auto bytes = embedded::descriptorSet();
    if (set.ParseFromArray(bytes.data(), static_cast<int>(bytes.size()))) {
      // Files come dependencies first (protoc --include_imports).
      for (const auto& file : set.file()) p->BuildFile(file);
    }
    return p;
  }();
  return *pool;
}

std::string oneParagraph(const std::string& comment) {
  std::istringstream in(comment);
  std::string line, out;
  while (std::getline(in, line)) {
    const auto begin = line.find_first_not_of(" \t");
    if (begin == std::string::npos) continue;
    const auto end = line.find_last_not_of(" \t");
    if (!out.empty()) out += ' ';
    out += line.substr(begin, end - begin + 1);
  }
  return out;
}

template <class D>
std::string commentOf(const D* descriptor) {
  google::protobuf::SourceLocation location;
  if (descriptor && descriptor->GetSourceLocation(&location)) {
    return oneParagraph(location.leading_comments);
  }
  return "";
}

}  // namespace

std::string leadingComment(const std::string& full_name) {
  const auto& pool = documentedPool();
  if (auto* s = pool.FindServiceByName(full_name)) return commentOf(s);
  if (auto* m = pool.FindMessageTypeByName(full_name)) return commentOf(m);
  if (auto* f = pool.FindFieldByName(full_name)) return commentOf(f);
  if (auto* x = pool.FindExtensionByName(full_name)) return commentOf(x);
  if (auto* e = pool.FindEnumTypeByName(full_name)) return commentOf(e);
  if (auto* v = pool.FindEnumValueByName(full_name)) return commentOf(v);
  if (auto* m = pool.FindMethodByName(full_name)) return commentOf(m);
  return "";
}

}  // namespace behaviorlib
