#pragma once

// CollisionWorld: the one question the vehicle dynamics asks of the
// environment. `World` (formats/world/world.h) implements it; the dynamics
// code depends only on this header, so it does not need the world's file
// format or ray casting.
//
//   const CollisionWorld& env = world;
//   if (env.collides(state.position_m, vehicle.radius_m)) crashed = true;

#include <Eigen/Core>

namespace behaviorlib::world {

/// Static geometry a vehicle can collide with. Positions in the world frame
/// (ENU, metres).
class CollisionWorld {
 public:
  virtual ~CollisionWorld() = default;
  virtual bool collides(const Eigen::Vector3d& position_m, double radius_m) const = 0;
};

}  // namespace behaviorlib::world
