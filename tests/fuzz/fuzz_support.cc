// The registrations of the real behaviors (fuzz_support.h), for the targets
// that check mission files and catalogs against them.

#include "fuzz_support.h"

#include <google/protobuf/descriptor.h>

#include <map>
#include <string>

#include "behaviorlib/parameters.h"
#include "behaviorlib/v1/behavior.pb.h"
#include "behaviorlib/v1/behaviors/attention_to_visual_markers.pb.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"
#include "behaviorlib/v1/behaviors/multi_sensor_fusion.pb.h"
#include "behaviorlib/v1/behaviors/navigation_with_lidar.pb.h"
#include "behaviorlib/v1/behaviors/operator_interaction.pb.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_mpc_control.pb.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_pid_control.pb.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_platform_control.pb.h"
#include "behaviorlib/v1/behaviors/swarm_interaction.pb.h"
#include "behaviorlib/v1/options.pb.h"

namespace behaviorlib::fuzz {
namespace {

namespace pb = google::protobuf;

struct Behaviors {
  std::map<std::string, v1::BehaviorDescription> descriptions;
  std::map<std::string, const pb::Descriptor*> parameter_types;
};

const Behaviors& behaviors() {
  static const Behaviors* const all = [] {
    auto* b = new Behaviors;
    // One message per file links the file (and registers all its types).
    const pb::Descriptor* const anchors[] = {
        v1::WaitParameters::descriptor(),
        v1::SelfLocalizeWithEkfSensorFusionParameters::descriptor(),
        v1::FollowPathParameters::descriptor(),
        v1::MoveVerticalWithPlatformControlParameters::descriptor(),
        v1::FollowPathWithMpcControlParameters::descriptor(),
        v1::InformRobotsParameters::descriptor(),
        v1::InformOperatorParameters::descriptor(),
        v1::PayAttentionToQrCodesParameters::descriptor(),
        v1::GeneratePathWithOccupancyGridParameters::descriptor(),
    };
    for (const pb::Descriptor* anchor : anchors) {
      const pb::FileDescriptor* file = anchor->file();
      for (int i = 0; i < file->message_type_count(); ++i) {
        const pb::Descriptor* type = file->message_type(i);
        if (!type->options().HasExtension(v1::declare)) continue;
        const std::string name = type->options().GetExtension(v1::declare).name();
        v1::BehaviorDescription& d = b->descriptions[name];
        d.set_name(name);
        d.set_parameters_type(type->full_name());
        params::describe(*type, d.mutable_parameters());
        b->parameter_types[name] = type;
      }
    }
    return b;
  }();
  return *all;
}

}  // namespace

const std::map<std::string, v1::BehaviorDescription>& behaviorDescriptions() {
  return behaviors().descriptions;
}

const google::protobuf::Descriptor* parameterTypeOf(const std::string& name) {
  const auto& types = behaviors().parameter_types;
  const auto type = types.find(name);
  return type == types.end() ? nullptr : type->second;
}

}  // namespace behaviorlib::fuzz
