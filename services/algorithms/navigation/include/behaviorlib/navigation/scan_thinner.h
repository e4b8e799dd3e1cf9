#pragma once

// ScanThinner: which lidar scans a map needs. Inserting a 2-D scan costs a
// few milliseconds (tens in open space, where every ray runs to the maximum
// range), and a lidar at 10 Hz in an accelerated simulation delivers tens a
// wall second: mapping every one kept a core busy and starved the rest of the
// stack. A scan is taken when at least min_interval_s of its own (simulated)
// time has passed since the last one taken, and the sensor has since moved
// still_distance_m or turned still_angle_rad; standing still, once every
// still_interval_s (a map of a scene that changes still follows it).
//
//   ScanThinner thinner(settings);
//   if (thinner.admit(stamp_ns, position, orientation)) insert(scan);

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <optional>

namespace behaviorlib::nav {

struct ScanThinningSettings {
  double min_interval_s = 0.2;
  double still_distance_m = 0.05;
  double still_angle_rad = 0.05;
  double still_interval_s = 1.0;
};

class ScanThinner {
 public:
  explicit ScanThinner(ScanThinningSettings settings = {}) : settings_(settings) {}

  /// Whether the scan stamped `stamp_ns`, taken from this pose, is to be
  /// inserted; remembers it when so. A stamp earlier than the last taken (a
  /// simulation reset) starts afresh.
  bool admit(int64_t stamp_ns, const Eigen::Vector3d& position_m,
             const Eigen::Quaterniond& orientation);
  /// The next scan is taken whatever it is (after the map was cleared).
  void reset() { last_.reset(); }

 private:
  struct Taken {
    int64_t stamp_ns;
    Eigen::Vector3d position_m;
    Eigen::Quaterniond orientation;
  };
  ScanThinningSettings settings_;
  std::optional<Taken> last_;
};

}  // namespace behaviorlib::nav
