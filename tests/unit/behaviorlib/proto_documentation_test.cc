// Every service, RPC, message, field, enum and enum value of the public API
// carries a comment, so that `grpcurl describe` (served by our reflection with
// source info) explains itself.

#include <google/protobuf/descriptor.h>
#include <google/protobuf/descriptor.pb.h>
#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "behaviorlib/documentation.h"
#include "behaviorlib/embedded_descriptors.h"

namespace behaviorlib {
namespace {

namespace pb = google::protobuf;

class Collector {
 public:
  std::vector<std::string> undocumented;

  void check(const std::string& full_name) {
    if (leadingComment(full_name).empty()) undocumented.push_back(full_name);
  }
  void message(const pb::Descriptor& m) {
    if (m.options().map_entry()) return;
    check(m.full_name());
    for (int i = 0; i < m.field_count(); ++i) check(m.field(i)->full_name());
    for (int i = 0; i < m.nested_type_count(); ++i) message(*m.nested_type(i));
    for (int i = 0; i < m.enum_type_count(); ++i) enumType(*m.enum_type(i));
  }
  void enumType(const pb::EnumDescriptor& e) {
    check(e.full_name());
    for (int i = 0; i < e.value_count(); ++i) check(e.value(i)->full_name());
  }
};

TEST(ProtoDocumentationTest, EveryElementOfThePublicApiHasAComment) {
  pb::FileDescriptorSet set;
  const auto bytes = embedded::descriptorSet();
  ASSERT_TRUE(set.ParseFromArray(bytes.data(), static_cast<int>(bytes.size())));
  pb::DescriptorPool pool;
  int files = 0;
  Collector collector;
  for (const auto& proto : set.file()) {
    const pb::FileDescriptor* file = pool.BuildFile(proto);
    ASSERT_NE(file, nullptr) << proto.name();
    if (file->package() != "behaviorlib.v1") continue;
    ++files;
    for (int i = 0; i < file->message_type_count(); ++i) collector.message(*file->message_type(i));
    for (int i = 0; i < file->enum_type_count(); ++i) collector.enumType(*file->enum_type(i));
    for (int i = 0; i < file->service_count(); ++i) {
      const pb::ServiceDescriptor& s = *file->service(i);
      collector.check(s.full_name());
      for (int j = 0; j < s.method_count(); ++j) collector.check(s.method(j)->full_name());
    }
    for (int i = 0; i < file->extension_count(); ++i) {
      collector.check(file->extension(i)->full_name());
    }
  }
  EXPECT_GE(files, 5);
  std::string list;
  for (const auto& name : collector.undocumented) list += "\n  " + name;
  EXPECT_TRUE(collector.undocumented.empty()) << "undocumented:" << list;
}

TEST(ProtoDocumentationTest, LeadingCommentIsOneTrimmedParagraph) {
  EXPECT_EQ(leadingComment("behaviorlib.v1.WaitParameters.duration_s"),
            "How long to wait, in seconds of the behavior's clock.");
  EXPECT_EQ(leadingComment("behaviorlib.v1.NoSuchThing"), "");
}

}  // namespace
}  // namespace behaviorlib
