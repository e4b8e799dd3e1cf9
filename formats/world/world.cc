#include "formats/world/world.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace behaviorlib::world {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

/// Rotates a world-frame vector into a box frame (by -yaw about z).
Eigen::Vector3d toBox(const Eigen::Vector3d& v, double c, double s) {
  return {c * v.x() + s * v.y(), -s * v.x() + c * v.y(), v.z()};
}

}  // namespace

std::array<Eigen::Vector3d, 4> Marker::corners() const {
  const Eigen::Vector3d r = right() * (size_m / 2.0);
  const Eigen::Vector3d u = up * (size_m / 2.0);
  return {center_m - r + u, center_m + r + u, center_m + r - u, center_m - r - u};
}

void World::addBox(Box box) {
  BoxFrame frame;
  frame.center = box.center_m;
  frame.half = box.size_m.cwiseAbs() / 2.0;
  frame.cos_yaw = std::cos(box.yaw_rad);
  frame.sin_yaw = std::sin(box.yaw_rad);
  frame.bound_radius = frame.half.norm();
  box_frames_.push_back(frame);
  boxes_.push_back(std::move(box));
}

void World::addPlane(Plane plane) {
  const double n = plane.normal.norm();
  plane.normal = n > 0.0 ? Eigen::Vector3d(plane.normal / n) : Eigen::Vector3d::UnitZ();
  planes_.push_back(std::move(plane));
}

void World::addMarker(Marker marker) {
  const double n = marker.normal.norm();
  marker.normal = n > 0.0 ? Eigen::Vector3d(marker.normal / n) : Eigen::Vector3d::UnitX();
  Eigen::Vector3d up = marker.up - marker.up.dot(marker.normal) * marker.normal;
  if (up.norm() < 1e-6) {
    const Eigen::Vector3d fallback =
        std::abs(marker.normal.z()) > 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitZ();
    up = fallback - fallback.dot(marker.normal) * marker.normal;
  }
  marker.up = up.normalized();
  markers_.push_back(std::move(marker));
}

const Box* World::findBox(std::string_view name) const {
  for (const Box& box : boxes_) {
    if (box.name == name) return &box;
  }
  return nullptr;
}

const Marker* World::findMarker(std::string_view name) const {
  for (const Marker& marker : markers_) {
    if (marker.name == name) return &marker;
  }
  return nullptr;
}

const StartPose* World::findStartPose(std::string_view robot_id) const {
  for (const StartPose& pose : start_poses_) {
    if (pose.robot_id == robot_id) return &pose;
  }
  return nullptr;
}

double World::castRay(const Eigen::Vector3d& origin_m, const Eigen::Vector3d& direction,
                      double max_range_m) const {
  double best = max_range_m;
  bool hit = false;

  // Ground z = 0.
  if (origin_m.z() < 0.0) return 0.0;
  if (direction.z() < 0.0) {
    const double t = -origin_m.z() / direction.z();
    if (t <= best) {
      best = t;
      hit = true;
    }
  }

  for (const Plane& plane : planes_) {
    const double side = plane.normal.dot(origin_m - plane.point_m);
    if (side < 0.0) return 0.0;
    const double denom = plane.normal.dot(direction);
    if (denom < 0.0) {
      const double t = -side / denom;
      if (t <= best) {
        best = t;
        hit = true;
      }
    }
  }

  for (const BoxFrame& box : box_frames_) {
    // Bounding sphere: cheap rejection.
    const Eigen::Vector3d to_center = box.center - origin_m;
    const double along = to_center.dot(direction);
    const double dist2 = to_center.squaredNorm();
    const double r2 = box.bound_radius * box.bound_radius;
    if (dist2 > r2) {
      if (along < 0.0) continue;
      if (dist2 - along * along > r2) continue;
      if (along - box.bound_radius > best) continue;
    }
    // Slab test in the box frame.
    const Eigen::Vector3d o = toBox(origin_m - box.center, box.cos_yaw, box.sin_yaw);
    const Eigen::Vector3d d = toBox(direction, box.cos_yaw, box.sin_yaw);
    double t_enter = -kInf;
    double t_exit = kInf;
    bool miss = false;
    for (int axis = 0; axis < 3; ++axis) {
      const double h = box.half[axis];
      if (std::abs(d[axis]) < 1e-15) {
        if (o[axis] < -h || o[axis] > h) {
          miss = true;
          break;
        }
        continue;
      }
      double t0 = (-h - o[axis]) / d[axis];
      double t1 = (h - o[axis]) / d[axis];
      if (t0 > t1) std::swap(t0, t1);
      t_enter = std::max(t_enter, t0);
      t_exit = std::min(t_exit, t1);
      if (t_enter > t_exit) {
        miss = true;
        break;
      }
    }
    if (miss || t_exit < 0.0) continue;
    if (t_enter < 0.0) return 0.0;  // the origin is inside this box
    if (t_enter <= best) {
      best = t_enter;
      hit = true;
    }
  }
  return hit ? best : kInf;
}

bool World::collides(const Eigen::Vector3d& position_m, double radius_m) const {
  return !collidingSurface(position_m, radius_m).empty();
}

std::string World::collidingSurface(const Eigen::Vector3d& position_m, double radius_m) const {
  if (position_m.z() < 0.0) return "ground";
  for (const Plane& plane : planes_) {
    if (plane.normal.dot(position_m - plane.point_m) < radius_m) return plane.name;
  }
  const double r2 = radius_m * radius_m;
  for (size_t i = 0; i < box_frames_.size(); ++i) {
    const BoxFrame& box = box_frames_[i];
    const Eigen::Vector3d q = toBox(position_m - box.center, box.cos_yaw, box.sin_yaw);
    const Eigen::Vector3d nearest = q.cwiseMax(-box.half).cwiseMin(box.half);
    const double d2 = (q - nearest).squaredNorm();
    // A point inside the box (d2 == 0) collides even with radius 0.
    if (d2 < r2 || (q.array().abs() < box.half.array()).all()) return boxes_[i].name;
  }
  return "";
}

}  // namespace behaviorlib::world
