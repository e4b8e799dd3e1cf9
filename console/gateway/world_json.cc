#include "world_json.h"

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>

#include "formats/world/world.h"

namespace behaviorlib::console {

namespace {

google::protobuf::Value vector3(const Eigen::Vector3d& v) {
  google::protobuf::Value out;
  auto& fields = *out.mutable_struct_value()->mutable_fields();
  fields["x"].set_number_value(v.x());
  fields["y"].set_number_value(v.y());
  fields["z"].set_number_value(v.z());
  return out;
}

}  // namespace

absl::StatusOr<std::string> worldJson(const std::string& path) {
  absl::StatusOr<world::World> world = world::loadWorld(path);
  if (!world.ok()) return world.status();
  google::protobuf::Struct root;
  auto* boxes = (*root.mutable_fields())["boxes"].mutable_list_value();
  for (const auto& box : world->boxes()) {
    auto& fields = *boxes->add_values()->mutable_struct_value()->mutable_fields();
    fields["name"].set_string_value(box.name);
    fields["kind"].set_string_value(box.kind == world::Box::Kind::kWall ? "wall" : "box");
    fields["center_m"] = vector3(box.center_m);
    fields["size_m"] = vector3(box.size_m);
    fields["yaw_rad"].set_number_value(box.yaw_rad);
  }
  auto* markers = (*root.mutable_fields())["markers"].mutable_list_value();
  for (const auto& marker : world->markers()) {
    auto& fields = *markers->add_values()->mutable_struct_value()->mutable_fields();
    fields["name"].set_string_value(marker.name);
    fields["text"].set_string_value(marker.text);
    fields["center_m"] = vector3(marker.center_m);
  }
  std::string json;
  if (!google::protobuf::util::MessageToJsonString(root, &json).ok()) {
    return absl::InternalError("cannot write the world as JSON");
  }
  return json;
}

}  // namespace behaviorlib::console
