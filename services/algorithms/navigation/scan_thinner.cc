#include "behaviorlib/navigation/scan_thinner.h"

namespace behaviorlib::nav {

bool ScanThinner::admit(int64_t stamp_ns, const Eigen::Vector3d& position_m,
                        const Eigen::Quaterniond& orientation) {
  bool take = !last_ || stamp_ns < last_->stamp_ns;
  if (!take) {
    const double elapsed_s = static_cast<double>(stamp_ns - last_->stamp_ns) * 1e-9;
    if (elapsed_s + 1e-9 < settings_.min_interval_s) return false;
    const bool moved = (position_m - last_->position_m).norm() >= settings_.still_distance_m ||
                       orientation.angularDistance(last_->orientation) >= settings_.still_angle_rad;
    take = moved || elapsed_s + 1e-9 >= settings_.still_interval_s;
  }
  if (take) last_ = Taken{stamp_ns, position_m, orientation};
  return take;
}

}  // namespace behaviorlib::nav
