#pragma once

// GroundRejection: which hits of a plane (2-D) lidar on a tilting vehicle may
// be the ground. A quadrotor tilts by 10 degrees and more when it speeds up
// or brakes; its lidar's plane then meets the floor along a line some metres
// away (1.3 m up, tilted 11 degrees: about 7 m). Those hits are computed with
// the pose estimate, whose altitude and attitude are not exact (a fused
// barometer: 0.15 m; roll and pitch: up to 2 degrees). A floor hit 7 m away
// then lands up to 0.4 m above the floor. Kept, it raised a wall column in
// the middle of a room, which closed the door behind it for the planner.
//
// So a hit is taken for the ground when it is at or below max_z_m, or when
// its ray surely descends (by more than the attitude error) and the hit is
// within the estimate's errors of that height: max_z_m + altitude_error_m +
// range * attitude_error_rad. A ray within the attitude error of level keeps
// its hits at any height above max_z_m:
// - in flight it cannot reach the floor within a lidar's range (1.3 m up, a
//   ray 3 degrees down meets it 25 m away), and a wall seen from 0.6 m up
//   stays a wall;
// - on the ground (the lidar 0.1 m up, within the altitude error of the
//   floor) every hit would be "near the floor": the rule kept only the
//   hits of rays the estimate tilted upwards, half a scan, and the lidar
//   SLAM's first matches slid 0.1 m on that half.
// What a surely descending ray hits low near the floor is dropped with the
// floor: a low obstacle, seen again from a level attitude.
//
//   GroundRejection ground;
//   if (ground.mayBeGround(hit.z(), direction.z(), range)) continue;

namespace behaviorlib::nav {

struct GroundRejection {
  /// A hit at or below this height (world, metres) is the ground.
  double max_z_m = 0.05;
  /// The pose estimate's altitude error, which a hit's height inherits.
  double altitude_error_m = 0.2;
  /// Its roll and pitch error, which moves a hit's height by range × this.
  double attitude_error_rad = 0.035;

  /// Whether a hit at height `z_m`, at `range_m` along a ray whose unit
  /// direction has vertical component `direction_z` (the sine of its
  /// elevation), may be the ground.
  bool mayBeGround(double z_m, double direction_z, double range_m) const {
    if (z_m <= max_z_m) return true;
    return direction_z < -attitude_error_rad &&
           z_m <= max_z_m + altitude_error_m + range_m * attitude_error_rad;
  }
};

}  // namespace behaviorlib::nav
