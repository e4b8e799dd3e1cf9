// loadWorld()/parseWorld(): the YAML world-file reader. Every problem is
// reported as "<file>:<line>: <what>: <problem>" using yaml-cpp's marks.

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <numbers>
#include <optional>
#include <set>
#include <sstream>
#include <utility>

#include "absl/status/status.h"
#include "behaviorlib/server_kit/confined_files.h"
#include "behaviorlib/server_kit/yaml_guard.h"
#include "formats/world/str_cat.h"
#include "formats/world/world.h"

namespace behaviorlib::world {
namespace {

using internal::strCat;

#define BL_RETURN_IF_ERROR(expr)       \
  do {                                 \
    absl::Status _status = (expr);     \
    if (!_status.ok()) return _status; \
  } while (false)

enum class Check { kAny, kPositive, kNonNegative };

/// The entries of one YAML mapping, after checking its keys.
struct MapView {
  YAML::Node node;
  std::string what;  ///< "box 'door'", for messages
  std::vector<std::pair<std::string, YAML::Node>> entries;

  std::optional<YAML::Node> find(std::string_view key) const {
    for (const auto& [k, v] : entries) {
      if (k == key) return v;
    }
    return std::nullopt;
  }
};

std::string joinKeys(const std::vector<std::string_view>& keys) {
  std::string out;
  for (std::string_view key : keys) {
    if (!out.empty()) out += ", ";
    out += key;
  }
  return out;
}

int lineOf(const YAML::Node& node) {
  const YAML::Mark mark = node.Mark();
  return mark.is_null() ? 1 : mark.line + 1;
}

bool toDouble(const YAML::Node& node, double* out) {
  if (!node.IsScalar()) return false;
  double value = 0.0;
  if (!YAML::convert<double>::decode(node, value) || !std::isfinite(value)) return false;
  *out = value;
  return true;
}

bool passes(double value, Check check) {
  switch (check) {
    case Check::kAny:
      return true;
    case Check::kPositive:
      return value > 0.0;
    case Check::kNonNegative:
      return value >= 0.0;
  }
  return false;
}

const char* describe(Check check) {
  switch (check) {
    case Check::kAny:
      return "";
    case Check::kPositive:
      return "positive ";
    case Check::kNonNegative:
      return "non-negative ";
  }
  return "";
}

class Parser {
 public:
  explicit Parser(std::string source) : source_(std::move(source)) {}

  absl::Status error(const YAML::Node& at, std::string_view what, std::string_view problem) const {
    return errorAtLine(lineOf(at), what, problem);
  }

  absl::Status errorAtLine(int line, std::string_view what, std::string_view problem) const {
    if (what.empty()) return absl::InvalidArgumentError(strCat(source_, ":", line, ": ", problem));
    return absl::InvalidArgumentError(strCat(source_, ":", line, ": ", what, ": ", problem));
  }

  /// Checks that `node` is a mapping whose keys are all in `allowed`, once each.
  absl::Status map(const YAML::Node& node, std::string what,
                   const std::vector<std::string_view>& allowed, MapView* out) const {
    if (!node.IsMap()) return error(node, what, "must be a mapping of keys to values");
    out->node = node;
    out->what = std::move(what);
    out->entries.clear();
    std::set<std::string> seen;
    for (const auto& entry : node) {
      const YAML::Node& key = entry.first;
      if (!key.IsScalar()) return error(key, out->what, "keys must be plain names");
      const std::string name = key.Scalar();
      if (std::find(allowed.begin(), allowed.end(), name) == allowed.end()) {
        return error(key, out->what,
                     strCat("unknown key '", name, "' (allowed: ", joinKeys(allowed), ")"));
      }
      if (!seen.insert(name).second) {
        return error(key, out->what, strCat("duplicate key '", name, "'"));
      }
      out->entries.emplace_back(name, entry.second);
    }
    return absl::OkStatus();
  }

  absl::Status missing(const MapView& m, std::string_view key) const {
    return error(m.node, m.what, strCat("missing required key '", key, "'"));
  }

  /// Reads a string; leaves `out` alone if the key is absent and not required.
  absl::Status getString(const MapView& m, std::string_view key, bool required,
                         std::string* out) const {
    const std::optional<YAML::Node> value = m.find(key);
    if (!value) return required ? missing(m, key) : absl::OkStatus();
    if (!value->IsScalar()) return error(*value, m.what, strCat(key, " must be a string"));
    *out = value->Scalar();
    return absl::OkStatus();
  }

  absl::Status getNumber(const MapView& m, std::string_view key, bool required, Check check,
                         double* out) const {
    const std::optional<YAML::Node> value = m.find(key);
    if (!value) return required ? missing(m, key) : absl::OkStatus();
    double number = 0.0;
    if (!toDouble(*value, &number) || !passes(number, check)) {
      return error(*value, m.what, strCat(key, " must be a ", describe(check), "number"));
    }
    *out = number;
    return absl::OkStatus();
  }

  /// Reads a list of exactly `n` numbers into out[0..n).
  absl::Status getNumbers(const MapView& m, std::string_view key, bool required, int n, Check check,
                          double* out) const {
    const std::optional<YAML::Node> value = m.find(key);
    if (!value) return required ? missing(m, key) : absl::OkStatus();
    const absl::Status bad = error(
        *value, m.what, strCat(key, " must be a list of ", n, " ", describe(check), "numbers"));
    if (!value->IsSequence() || static_cast<int>(value->size()) != n) return bad;
    for (int i = 0; i < n; ++i) {
      double number = 0.0;
      if (!toDouble((*value)[i], &number) || !passes(number, check)) return bad;
      out[i] = number;
    }
    return absl::OkStatus();
  }

  absl::Status getVector3(const MapView& m, std::string_view key, bool required, Check check,
                          Eigen::Vector3d* out) const {
    return getNumbers(m, key, required, 3, check, out->data());
  }

  absl::Status getColor(const MapView& m, std::string_view key, Rgb* out) const {
    const std::optional<YAML::Node> value = m.find(key);
    if (!value) return absl::OkStatus();
    const absl::Status bad =
        error(*value, m.what, strCat(key, " must be a list of 3 integers 0..255 [r, g, b]"));
    if (!value->IsSequence() || value->size() != 3) return bad;
    int channels[3];
    for (int i = 0; i < 3; ++i) {
      const YAML::Node item = (*value)[i];
      if (!item.IsScalar() || !YAML::convert<int>::decode(item, channels[i]) || channels[i] < 0 ||
          channels[i] > 255) {
        return bad;
      }
    }
    *out = Rgb{static_cast<std::uint8_t>(channels[0]), static_cast<std::uint8_t>(channels[1]),
               static_cast<std::uint8_t>(channels[2])};
    return absl::OkStatus();
  }

  /// A list under `key` (absent or null: an empty list). Returned by value:
  /// assigning to an existing YAML::Node would rebind the node it refers to.
  absl::StatusOr<YAML::Node> getList(const MapView& m, std::string_view key) const {
    const std::optional<YAML::Node> value = m.find(key);
    if (!value || value->IsNull()) return YAML::Node(YAML::NodeType::Sequence);
    if (!value->IsSequence()) return error(*value, m.what, strCat(key, " must be a list"));
    return *value;
  }

  /// Reads `name` (required) and forms "<kind> '<name>'" for messages.
  absl::Status named(const YAML::Node& node, std::string_view kind, std::size_t index,
                     const std::vector<std::string_view>& allowed, std::string_view name_key,
                     MapView* out, std::string* name) const {
    const std::string anonymous = strCat(kind, " #", index + 1);
    if (!node.IsMap()) return error(node, anonymous, "must be a mapping of keys to values");
    std::string what = anonymous;
    const YAML::Node name_node = node[std::string(name_key)];
    if (name_node && name_node.IsScalar()) what = strCat(kind, " '", name_node.Scalar(), "'");
    BL_RETURN_IF_ERROR(map(node, what, allowed, out));
    BL_RETURN_IF_ERROR(getString(*out, name_key, true, name));
    if (name->empty()) return error(*out->find(name_key), out->what, "name must not be empty");
    return absl::OkStatus();
  }

 private:
  std::string source_;
};

/// Which face of `box` the marker lies on; fills `center` with the marker's
/// centre snapped onto the face.
absl::Status placeOnBox(const Parser& parser, const MapView& m, const Box& box,
                        const Marker& marker, Eigen::Vector3d* center) {
  const double c = std::cos(box.yaw_rad);
  const double s = std::sin(box.yaw_rad);
  auto to_box = [&](const Eigen::Vector3d& v) {
    return Eigen::Vector3d(c * v.x() + s * v.y(), -s * v.x() + c * v.y(), v.z());
  };
  auto to_world = [&](const Eigen::Vector3d& v) {
    return Eigen::Vector3d(c * v.x() - s * v.y(), s * v.x() + c * v.y(), v.z());
  };
  const Eigen::Vector3d n = to_box(marker.normal.normalized());
  int axis = 0;
  n.cwiseAbs().maxCoeff(&axis);
  static const char* kFaces[3][2] = {{"-x", "+x"}, {"-y", "+y"}, {"-z", "+z"}};
  const int sign = n[axis] > 0.0 ? 1 : 0;
  const std::string face = kFaces[axis][sign];
  if (std::abs(n[axis]) < std::cos(2.0 * std::numbers::pi / 180.0)) {
    return parser.error(*m.find("normal"), m.what,
                        strCat("normal matches no face of box '", box.name,
                               "' (it must be perpendicular to one, within 2 degrees)"));
  }
  const Eigen::Vector3d half = box.size_m / 2.0;
  Eigen::Vector3d local = to_box(marker.center_m - box.center_m);
  const double face_offset = (sign ? 1.0 : -1.0) * half[axis];
  const double gap = std::abs(local[axis] - face_offset);
  if (gap > 0.02) {
    return parser.error(*m.find("center_m"), m.what,
                        strCat("center_m is ", gap, " m from the ", face, " face of box '",
                               box.name, "' (it must lie on it, within 0.02 m)"));
  }
  local[axis] = face_offset;
  // The whole square must fit on the face.
  Marker snapped = marker;
  snapped.center_m = box.center_m + to_world(local);
  for (const Eigen::Vector3d& corner : snapped.corners()) {
    const Eigen::Vector3d q = to_box(corner - box.center_m);
    for (int i = 0; i < 3; ++i) {
      if (i != axis && std::abs(q[i]) > half[i] + 0.01) {
        return parser.error(
            *m.find("size_m"), m.what,
            strCat("the marker does not fit on the ", face, " face of box '", box.name, "'"));
      }
    }
  }
  *center = snapped.center_m;
  return absl::OkStatus();
}

absl::Status parseBoxes(const Parser& parser, const YAML::Node& list, World* world,
                        std::set<std::string>* names) {
  for (std::size_t i = 0; i < list.size(); ++i) {
    MapView m;
    Box box;
    BL_RETURN_IF_ERROR(parser.named(list[i], "box", i,
                                    {"name", "center_m", "size_m", "yaw_rad", "color"}, "name", &m,
                                    &box.name));
    if (!names->insert(box.name).second) {
      return parser.error(*m.find("name"), m.what, "another box or wall has this name");
    }
    BL_RETURN_IF_ERROR(parser.getVector3(m, "center_m", true, Check::kAny, &box.center_m));
    BL_RETURN_IF_ERROR(parser.getVector3(m, "size_m", true, Check::kPositive, &box.size_m));
    BL_RETURN_IF_ERROR(parser.getNumber(m, "yaw_rad", false, Check::kAny, &box.yaw_rad));
    BL_RETURN_IF_ERROR(parser.getColor(m, "color", &box.color));
    box.kind = Box::Kind::kBox;
    world->addBox(std::move(box));
  }
  return absl::OkStatus();
}

absl::Status parseWalls(const Parser& parser, const YAML::Node& list, World* world,
                        std::set<std::string>* names) {
  for (std::size_t i = 0; i < list.size(); ++i) {
    MapView m;
    std::string name;
    BL_RETURN_IF_ERROR(parser.named(
        list[i], "wall", i,
        {"name", "from_m", "to_m", "height_m", "thickness_m", "base_z_m", "color", "doors"}, "name",
        &m, &name));
    Eigen::Vector2d from;
    Eigen::Vector2d to;
    double height = 0.0;
    double thickness = 0.2;
    double base_z = 0.0;
    Rgb color{215, 205, 185};
    BL_RETURN_IF_ERROR(parser.getNumbers(m, "from_m", true, 2, Check::kAny, from.data()));
    BL_RETURN_IF_ERROR(parser.getNumbers(m, "to_m", true, 2, Check::kAny, to.data()));
    BL_RETURN_IF_ERROR(parser.getNumber(m, "height_m", true, Check::kPositive, &height));
    BL_RETURN_IF_ERROR(parser.getNumber(m, "thickness_m", false, Check::kPositive, &thickness));
    BL_RETURN_IF_ERROR(parser.getNumber(m, "base_z_m", false, Check::kAny, &base_z));
    BL_RETURN_IF_ERROR(parser.getColor(m, "color", &color));
    const double length = (to - from).norm();
    if (length < 1e-6) return parser.error(*m.find("to_m"), m.what, "from_m and to_m must differ");
    const Eigen::Vector2d along = (to - from) / length;
    const double yaw = std::atan2(along.y(), along.x());

    // Openings, sorted along the wall, checked for overlaps.
    struct Opening {
      double begin, end, height;
      int line;  // not a YAML::Node: sorting assigns, and assigning rebinds nodes
    };
    std::vector<Opening> openings;
    const absl::StatusOr<YAML::Node> door_list = parser.getList(m, "doors");
    if (!door_list.ok()) return door_list.status();
    const YAML::Node& doors = *door_list;
    for (std::size_t k = 0; k < doors.size(); ++k) {
      MapView d;
      const std::string what = strCat(m.what, " door #", k + 1);
      BL_RETURN_IF_ERROR(parser.map(doors[k], what, {"offset_m", "width_m", "height_m"}, &d));
      double offset = 0.0;
      double width = 0.0;
      double door_height = height;
      BL_RETURN_IF_ERROR(parser.getNumber(d, "offset_m", true, Check::kAny, &offset));
      BL_RETURN_IF_ERROR(parser.getNumber(d, "width_m", true, Check::kPositive, &width));
      BL_RETURN_IF_ERROR(parser.getNumber(d, "height_m", false, Check::kPositive, &door_height));
      if (offset - width / 2.0 < 0.0 || offset + width / 2.0 > length) {
        return parser.error(
            doors[k], what,
            strCat("the opening [", offset - width / 2.0, ", ", offset + width / 2.0,
                   "] m does not fit in the wall (0 to ", length, " m)"));
      }
      if (door_height > height) {
        return parser.error(*d.find("height_m"), what, "height_m exceeds the wall's height_m");
      }
      openings.push_back(
          {offset - width / 2.0, offset + width / 2.0, door_height, lineOf(doors[k])});
    }
    std::sort(openings.begin(), openings.end(),
              [](const Opening& a, const Opening& b) { return a.begin < b.begin; });
    for (std::size_t k = 1; k < openings.size(); ++k) {
      if (openings[k].begin < openings[k - 1].end) {
        return parser.errorAtLine(openings[k].line, m.what, "doors overlap");
      }
    }

    // Solid spans between openings; the ends extend by half the thickness so
    // walls meeting at a point close the corner.
    auto add = [&](std::string box_name, double begin, double end, double z0,
                   double z1) -> absl::Status {
      if (end - begin < 1e-6 || z1 - z0 < 1e-6) return absl::OkStatus();
      if (!names->insert(box_name).second) {
        return parser.error(*m.find("name"), m.what,
                            strCat("another box or wall has the name '", box_name, "'"));
      }
      Box box;
      box.name = std::move(box_name);
      const Eigen::Vector2d mid = from + along * ((begin + end) / 2.0);
      box.center_m = {mid.x(), mid.y(), (z0 + z1) / 2.0};
      box.size_m = {end - begin, thickness, z1 - z0};
      box.yaw_rad = yaw;
      box.color = color;
      box.kind = Box::Kind::kWall;
      world->addBox(std::move(box));
      return absl::OkStatus();
    };
    const double top = base_z + height;
    if (openings.empty()) {
      BL_RETURN_IF_ERROR(add(name, -thickness / 2.0, length + thickness / 2.0, base_z, top));
      continue;
    }
    double cursor = -thickness / 2.0;
    for (std::size_t k = 0; k < openings.size(); ++k) {
      const Opening& o = openings[k];
      BL_RETURN_IF_ERROR(add(strCat(name, "/segment", k), cursor, o.begin, base_z, top));
      BL_RETURN_IF_ERROR(add(strCat(name, "/lintel", k), o.begin, o.end, base_z + o.height, top));
      const Eigen::Vector2d mid = from + along * ((o.begin + o.end) / 2.0);
      world->addDoor(Door{name, {mid.x(), mid.y(), base_z}, o.end - o.begin, o.height, yaw});
      cursor = o.end;
    }
    BL_RETURN_IF_ERROR(add(strCat(name, "/segment", openings.size()), cursor,
                           length + thickness / 2.0, base_z, top));
  }
  return absl::OkStatus();
}

absl::Status parsePlanes(const Parser& parser, const YAML::Node& list, World* world) {
  std::set<std::string> names;
  for (std::size_t i = 0; i < list.size(); ++i) {
    MapView m;
    Plane plane;
    BL_RETURN_IF_ERROR(parser.named(list[i], "plane", i, {"name", "point_m", "normal", "color"},
                                    "name", &m, &plane.name));
    if (!names.insert(plane.name).second) {
      return parser.error(*m.find("name"), m.what, "another plane has this name");
    }
    BL_RETURN_IF_ERROR(parser.getVector3(m, "point_m", true, Check::kAny, &plane.point_m));
    BL_RETURN_IF_ERROR(parser.getVector3(m, "normal", true, Check::kAny, &plane.normal));
    if (plane.normal.norm() < 1e-9) {
      return parser.error(*m.find("normal"), m.what, "normal must not be zero");
    }
    BL_RETURN_IF_ERROR(parser.getColor(m, "color", &plane.color));
    world->addPlane(std::move(plane));
  }
  return absl::OkStatus();
}

absl::Status parseMarkers(const Parser& parser, const YAML::Node& list, World* world) {
  std::set<std::string> names;
  for (std::size_t i = 0; i < list.size(); ++i) {
    MapView m;
    Marker marker;
    BL_RETURN_IF_ERROR(parser.named(
        list[i], "marker", i, {"name", "text", "center_m", "normal", "up", "size_m", "attached_to"},
        "name", &m, &marker.name));
    if (!names.insert(marker.name).second) {
      return parser.error(*m.find("name"), m.what, "another marker has this name");
    }
    BL_RETURN_IF_ERROR(parser.getString(m, "text", true, &marker.text));
    const bool printable = std::all_of(marker.text.begin(), marker.text.end(),
                                       [](char ch) { return ch >= 0x20 && ch <= 0x7e; });
    if (marker.text.empty() || marker.text.size() > 200 || !printable) {
      return parser.error(*m.find("text"), m.what,
                          "text must be 1 to 200 printable ASCII characters");
    }
    BL_RETURN_IF_ERROR(parser.getVector3(m, "center_m", true, Check::kAny, &marker.center_m));
    BL_RETURN_IF_ERROR(parser.getVector3(m, "normal", true, Check::kAny, &marker.normal));
    if (marker.normal.norm() < 1e-9) {
      return parser.error(*m.find("normal"), m.what, "normal must not be zero");
    }
    marker.up = Eigen::Vector3d::Zero();  // default chosen by World::addMarker
    BL_RETURN_IF_ERROR(parser.getVector3(m, "up", false, Check::kAny, &marker.up));
    if (m.find("up") && marker.up.cross(marker.normal).norm() < 1e-6 * marker.up.norm() + 1e-12) {
      return parser.error(*m.find("up"), m.what, "up must not be zero or parallel to normal");
    }
    BL_RETURN_IF_ERROR(parser.getNumber(m, "size_m", true, Check::kPositive, &marker.size_m));
    BL_RETURN_IF_ERROR(parser.getString(m, "attached_to", false, &marker.attached_to));
    if (!marker.attached_to.empty()) {
      const Box* box = world->findBox(marker.attached_to);
      if (box == nullptr) {
        return parser.error(*m.find("attached_to"), m.what,
                            strCat("attached_to names no box: '", marker.attached_to, "'"));
      }
      // Orthonormalize first so that the fit check uses the final square.
      World scratch;
      scratch.addMarker(marker);
      Marker placed = scratch.markers().front();
      BL_RETURN_IF_ERROR(placeOnBox(parser, m, *box, placed, &marker.center_m));
    }
    world->addMarker(std::move(marker));
  }
  return absl::OkStatus();
}

absl::Status parseStartPoses(const Parser& parser, const YAML::Node& list, World* world) {
  for (std::size_t i = 0; i < list.size(); ++i) {
    MapView m;
    StartPose pose;
    BL_RETURN_IF_ERROR(parser.named(list[i], "start pose", i, {"robot_id", "position_m", "yaw_rad"},
                                    "robot_id", &m, &pose.robot_id));
    if (world->findStartPose(pose.robot_id) != nullptr) {
      return parser.error(*m.find("robot_id"), m.what, "another start pose has this robot_id");
    }
    BL_RETURN_IF_ERROR(parser.getVector3(m, "position_m", true, Check::kAny, &pose.position_m));
    BL_RETURN_IF_ERROR(parser.getNumber(m, "yaw_rad", false, Check::kAny, &pose.yaw_rad));
    if (pose.position_m.z() < 0.0) {
      return parser.error(*m.find("position_m"), m.what, "position_m is below the ground");
    }
    const std::string inside = world->collidingSurface(pose.position_m, 0.0);
    if (!inside.empty()) {
      return parser.error(*m.find("position_m"), m.what,
                          strCat("position_m is inside '", inside, "'"));
    }
    world->addStartPose(std::move(pose));
  }
  return absl::OkStatus();
}

absl::StatusOr<World> parseRoot(const Parser& parser, const YAML::Node& root) {
  if (!root || root.IsNull()) return parser.errorAtLine(1, "", "the world file is empty");
  MapView m;
  BL_RETURN_IF_ERROR(parser.map(root, "world",
                                {"name", "description", "sky_color", "ground_color", "boxes",
                                 "walls", "planes", "markers", "start_poses"},
                                &m));
  std::string name;
  BL_RETURN_IF_ERROR(parser.getString(m, "name", true, &name));
  if (name.empty()) return parser.error(*m.find("name"), m.what, "name must not be empty");
  World world(name);
  std::string description;
  BL_RETURN_IF_ERROR(parser.getString(m, "description", false, &description));
  world.setDescription(std::move(description));
  Rgb sky = world.skyColor();
  Rgb ground = world.groundColor();
  BL_RETURN_IF_ERROR(parser.getColor(m, "sky_color", &sky));
  BL_RETURN_IF_ERROR(parser.getColor(m, "ground_color", &ground));
  world.setSkyColor(sky);
  world.setGroundColor(ground);

  // Geometry first: markers and start poses are checked against it.
  std::set<std::string> box_names;
  const absl::StatusOr<YAML::Node> boxes = parser.getList(m, "boxes");
  if (!boxes.ok()) return boxes.status();
  BL_RETURN_IF_ERROR(parseBoxes(parser, *boxes, &world, &box_names));
  const absl::StatusOr<YAML::Node> walls = parser.getList(m, "walls");
  if (!walls.ok()) return walls.status();
  BL_RETURN_IF_ERROR(parseWalls(parser, *walls, &world, &box_names));
  const absl::StatusOr<YAML::Node> planes = parser.getList(m, "planes");
  if (!planes.ok()) return planes.status();
  BL_RETURN_IF_ERROR(parsePlanes(parser, *planes, &world));
  const absl::StatusOr<YAML::Node> markers = parser.getList(m, "markers");
  if (!markers.ok()) return markers.status();
  BL_RETURN_IF_ERROR(parseMarkers(parser, *markers, &world));
  const absl::StatusOr<YAML::Node> start_poses = parser.getList(m, "start_poses");
  if (!start_poses.ok()) return start_poses.status();
  BL_RETURN_IF_ERROR(parseStartPoses(parser, *start_poses, &world));
  return world;
}

}  // namespace

absl::StatusOr<World> parseWorld(std::string_view yaml_text, std::string_view source_name) {
  const Parser parser{std::string(source_name)};
  YAML::Node root;
  BL_RETURN_IF_ERROR(server_kit::loadYaml(yaml_text, std::string(source_name), &root));
  absl::StatusOr<World> world = absl::InternalError("not parsed");
  BL_RETURN_IF_ERROR(server_kit::guardYamlParse(std::string(source_name), [&] {
    world = parseRoot(parser, root);
    return absl::OkStatus();
  }));
  if (world.ok()) world->setSourcePath(std::string(source_name));
  return world;
}

absl::StatusOr<World> loadWorld(const std::string& path) {
  // The cap keeps a path such as /dev/zero or a huge file from being read whole.
  absl::StatusOr<std::string> text = server_kit::readFileCapped(path, kMaxWorldFileBytes);
  if (!text.ok()) return text.status();
  return parseWorld(*text, path);
}

#undef BL_RETURN_IF_ERROR

}  // namespace behaviorlib::world
