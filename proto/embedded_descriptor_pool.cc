#include "behaviorlib/embedded_descriptor_pool.h"

#include <google/protobuf/descriptor.pb.h>
#include <google/protobuf/descriptor_database.h>

#include "behaviorlib/embedded_descriptors.h"

namespace behaviorlib::embedded {

namespace {

struct Pool {
  Pool() : pool(&database) {
    google::protobuf::FileDescriptorSet set;
    const std::string_view bytes = descriptorSet();
    if (set.ParseFromArray(bytes.data(), static_cast<int>(bytes.size()))) {
      for (const auto& file : set.file()) database.Add(file);
    }
  }
  google::protobuf::SimpleDescriptorDatabase database;
  google::protobuf::DescriptorPool pool;
};

}  // namespace

const google::protobuf::DescriptorPool& descriptorPool() {
  static const Pool* const instance = new Pool();
  return instance->pool;
}

}  // namespace behaviorlib::embedded
