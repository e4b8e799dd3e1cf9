#pragma once

// World: the static environment of the simulator — boxes (and walls, which
// are boxes), infinite planes, QR markers printed on surfaces, and the start
// poses of the robots — loaded from a YAML world file (format documented in
// simulator/worlds/README.md), with ray casting for range sensors and sphere
// collision for the dynamics.
//
//   absl::StatusOr<World> world = loadWorld("simulator/worlds/rooms.yaml");
//   if (!world.ok()) return world.status();  // "rooms.yaml:12: box 'door': ..."
//   const StartPose* start = world->findStartPose("drone1");
//   double range_m = world->castRay(start->position_m, Eigen::Vector3d::UnitX(), 30.0);
//   bool crashed = world->collides(position_m, 0.3);
//
// Frames and units: world ENU (x east, y north, z up), metres, radians, yaw
// counter-clockwise from +x. The ground is the plane z = 0, always present.
// A World is immutable once built and safe to read from several threads.

#include <Eigen/Core>
#include <Eigen/Geometry>  // cross()
#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "formats/world/collision_world.h"

namespace behaviorlib::world {

/// A colour, 0..255 per channel (red, green, blue; not OpenCV's BGR order).
struct Rgb {
  std::uint8_t r = 0;
  std::uint8_t g = 0;
  std::uint8_t b = 0;
  friend bool operator==(const Rgb&, const Rgb&) = default;
};

/// A solid box, rotated about the vertical axis by `yaw_rad`.
struct Box {
  enum class Kind {
    kBox,   ///< from `boxes:` in the world file
    kWall,  ///< a segment (or a lintel above a door) from `walls:`
  };
  std::string name;
  Eigen::Vector3d center_m = Eigen::Vector3d::Zero();  ///< world frame
  Eigen::Vector3d size_m = Eigen::Vector3d::Ones();    ///< full extents along the box's x, y, z
  double yaw_rad = 0.0;  ///< rotation of the box's x axis from world +x, counter-clockwise
  Rgb color{170, 170, 170};
  Kind kind = Kind::kBox;
};

/// A door: an opening in a wall (information for planners; the wall's boxes
/// already leave the gap).
struct Door {
  std::string wall;                                    ///< name of the wall
  Eigen::Vector3d center_m = Eigen::Vector3d::Zero();  ///< centre of the opening at floor level
  double width_m = 0.0;
  double height_m = 0.0;
  double yaw_rad = 0.0;  ///< direction of the wall (from its `from_m` to its `to_m`)
};

/// An infinite plane through `point_m`. The half-space behind it (opposite to
/// `normal`) is solid: the ground is {point (0,0,0), normal +z}.
struct Plane {
  std::string name;
  Eigen::Vector3d point_m = Eigen::Vector3d::Zero();
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();  ///< unit
  Rgb color{120, 120, 120};
};

/// A square QR code printed on a surface. `size_m` is the side of the printed
/// square including its white quiet zone (4 modules on each side).
struct Marker {
  std::string name;
  std::string text;                                    ///< what the QR code encodes
  Eigen::Vector3d center_m = Eigen::Vector3d::Zero();  ///< world frame, on the surface
  Eigen::Vector3d normal = Eigen::Vector3d::UnitX();   ///< unit; the side the code is printed on
  Eigen::Vector3d up =
      Eigen::Vector3d::UnitZ();  ///< unit, in the marker plane: the code's top edge
  double size_m = 0.5;
  std::string attached_to;  ///< name of the box it is printed on, or ""

  /// Right-hand direction of the code as seen from its front: up x normal.
  Eigen::Vector3d right() const { return up.cross(normal); }
  /// Corners as seen from the front: top-left, top-right, bottom-right, bottom-left.
  std::array<Eigen::Vector3d, 4> corners() const;
};

/// Where a robot starts (on the ground or in the air).
struct StartPose {
  std::string robot_id;
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();
  double yaw_rad = 0.0;
};

/// The static world. Build it with loadWorld() or with the add*() methods.
class World : public CollisionWorld {
 public:
  World() = default;
  explicit World(std::string name) : name_(std::move(name)) {}

  const std::string& name() const { return name_; }
  const std::string& description() const { return description_; }
  void setDescription(std::string description) { description_ = std::move(description); }
  /// The file this world was loaded from, or "".
  const std::string& sourcePath() const { return source_path_; }
  void setSourcePath(std::string path) { source_path_ = std::move(path); }

  Rgb skyColor() const { return sky_color_; }
  Rgb groundColor() const { return ground_color_; }
  void setSkyColor(Rgb color) { sky_color_ = color; }
  void setGroundColor(Rgb color) { ground_color_ = color; }

  /// Adds a box. Precondition: positive sizes (loadWorld checks them).
  void addBox(Box box);
  /// Adds an infinite plane; its normal is normalized.
  void addPlane(Plane plane);
  /// Adds a marker; `normal` is normalized and `up` made orthonormal to it. A
  /// zero or parallel `up` becomes world +z projected on the plane, or +x for a
  /// marker facing up or down.
  void addMarker(Marker marker);
  void addDoor(Door door) { doors_.push_back(std::move(door)); }
  void addStartPose(StartPose pose) { start_poses_.push_back(std::move(pose)); }

  const std::vector<Box>& boxes() const { return boxes_; }
  const std::vector<Plane>& planes() const { return planes_; }  ///< not the ground
  const std::vector<Marker>& markers() const { return markers_; }
  const std::vector<Door>& doors() const { return doors_; }
  const std::vector<StartPose>& startPoses() const { return start_poses_; }

  const Box* findBox(std::string_view name) const;
  const Marker* findMarker(std::string_view name) const;
  const StartPose* findStartPose(std::string_view robot_id) const;

  /// Distance along the ray from `origin_m` in the unit `direction` to the
  /// nearest surface (box, ground, plane) within `max_range_m`, else +inf.
  /// A ray starting inside a solid returns 0. Markers are flat on their
  /// surfaces and not hit separately.
  double castRay(const Eigen::Vector3d& origin_m, const Eigen::Vector3d& direction,
                 double max_range_m) const;

  /// True if the sphere overlaps a box or the solid side of a plane, or its
  /// centre is below the ground (touching the ground from above is not a
  /// collision: landed vehicles rest on it).
  bool collides(const Eigen::Vector3d& position_m, double radius_m) const override;

  /// Name of the first box the sphere overlaps ("ground" or a plane's name
  /// for those), or "" if none. For diagnostics.
  std::string collidingSurface(const Eigen::Vector3d& position_m, double radius_m) const;

 private:
  /// Per box, what ray casting and collision need without trigonometry.
  struct BoxFrame {
    Eigen::Vector3d center;
    Eigen::Vector3d half;
    double cos_yaw;
    double sin_yaw;
    double bound_radius;  ///< radius of the bounding sphere
  };

  std::string name_;
  std::string description_;
  std::string source_path_;
  Rgb sky_color_{150, 200, 235};
  Rgb ground_color_{105, 130, 90};
  std::vector<Box> boxes_;
  std::vector<BoxFrame> box_frames_;
  std::vector<Plane> planes_;
  std::vector<Marker> markers_;
  std::vector<Door> doors_;
  std::vector<StartPose> start_poses_;
};

/// Largest world file read (a world is a few kilobytes).
inline constexpr size_t kMaxWorldFileBytes = 4 << 20;

/// Loads a world file (at most kMaxWorldFileBytes). Errors (kNotFound for a
/// missing file, else kInvalidArgument) read "<path>:<line>: <what>: <problem>", e.g.
/// "worlds/x.yaml:12: box 'door': size_m must be a list of 3 positive numbers".
absl::StatusOr<World> loadWorld(const std::string& path);

/// Parses world YAML text; `source_name` stands for the file in errors.
absl::StatusOr<World> parseWorld(std::string_view yaml_text, std::string_view source_name);

}  // namespace behaviorlib::world
