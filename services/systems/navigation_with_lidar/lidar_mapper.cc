#include "behaviorlib/navigation_with_lidar/lidar_mapper.h"

#include <google/protobuf/util/time_util.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "behaviorlib/flight_common/topics.h"

namespace behaviorlib::nav {
namespace {

constexpr int64_t kPoseHistoryNs = 1'000'000'000;
/// A scan newer than the newest pose by less than this waits for its pose
/// (on its way); a pose stream that stopped longer ago is not waited for.
constexpr int64_t kPoseWaitWindowNs = 200'000'000;

Eigen::Vector3d vec(const v1::Vector3& v) { return {v.x(), v.y(), v.z()}; }

Eigen::Quaterniond quat(const v1::Quaternion& q) {
  return Eigen::Quaterniond(q.w(), q.x(), q.y(), q.z()).normalized();
}

}  // namespace

int64_t stampNs(const v1::Header& header) {
  return google::protobuf::util::TimeUtil::TimestampToNanoseconds(header.stamp());
}

absl::Status MapperSettings::configure(const config::v1::MappingConfig& mapping) {
  if (mapping.lidar_mount_m_size() != 3) {
    return absl::InvalidArgumentError(
        "mapping: lidar_mount_m must be a list of 3 numbers [x, y, z] (body frame, metres)");
  }
  resolution_m = mapping.resolution_m();
  max_range_m = mapping.max_range_m();
  lidar_mount_m = {mapping.lidar_mount_m(0), mapping.lidar_mount_m(1), mapping.lidar_mount_m(2)};
  ground.max_z_m = mapping.ground_max_z_m();
  ground.altitude_error_m = mapping.ground_altitude_error_m();
  ground.attitude_error_rad = mapping.ground_attitude_error_rad();
  hit_depth_m = mapping.hit_depth_m();
  column_min_z_m = mapping.column_min_z_m();
  column_max_z_m = mapping.column_max_z_m();
  planning_min_z_m = mapping.planning_min_z_m();
  planning_max_z_m = mapping.planning_max_z_m();
  pose_match_s = mapping.pose_match_s();
  max_pose_stddev_m = mapping.max_pose_stddev_m();
  scan_queue_size = mapping.scan_queue_size();
  thinning.min_interval_s = mapping.min_scan_interval_s();
  thinning.still_distance_m = mapping.still_distance_m();
  thinning.still_angle_rad = mapping.still_angle_rad();
  thinning.still_interval_s = mapping.still_scan_interval_s();
  if (planning_max_z_m <= planning_min_z_m) {
    return absl::InvalidArgumentError(
        "mapping: planning_max_z_m must be greater than planning_min_z_m");
  }
  if (column_max_z_m <= column_min_z_m) {
    return absl::InvalidArgumentError(
        "mapping: column_max_z_m must be greater than column_min_z_m");
  }
  return absl::OkStatus();
}

LidarMapper::LidarMapper(channel::ChannelClient* channel, std::string robot_id,
                         MapperSettings settings)
    : channel_(channel),
      robot_id_(std::move(robot_id)),
      settings_(settings),
      map_(MapOptions{.resolution_m = settings.resolution_m}),
      columns_(WallColumnSettings{.resolution_m = settings.resolution_m,
                                  .min_z_m = settings.column_min_z_m,
                                  .max_z_m = settings.column_max_z_m,
                                  .max_hit_z_m = settings.planning_max_z_m}),
      thinner_(settings.thinning) {
  if (!channel_) return;
  thread_ = std::thread([this] { run(); });
  pose_sub_ = channel_->subscribeTyped<v1::PoseStamped>(
      poseTopic(), {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 200},
      [this](const v1::PoseStamped& p) { onPose(p); });
  // The scans are subscribed to only while pose estimates come (see
  // followScans): without a pose no scan can be mapped, and an idle stack
  // then carries no lidar data at all.
}

LidarMapper::~LidarMapper() {
  // The mapping thread first (it makes and drops the scan subscription),
  // then the readers (their callbacks take mutex_).
  {
    absl::MutexLock lock(&mutex_);
    stopping_ = true;
  }
  if (thread_.joinable()) thread_.join();
  scan_sub_.reset();
  pose_sub_.reset();
}

void LidarMapper::followScans(bool want) {
  if (want == (scan_sub_ != nullptr)) return;
  if (!want) {
    scan_sub_.reset();
    return;
  }
  scan_sub_ = channel_->subscribeTyped<v1::LaserScan>(
      scanTopic(),
      {.mode = v1::DELIVERY_MODE_QUEUE,
       .queue_size = static_cast<uint32_t>(std::max(1, settings_.scan_queue_size))},
      [this](const v1::LaserScan& s) { onScan(s); });
}

std::string LidarMapper::scanTopic() const { return "robots/" + robot_id_ + "/lidar/scan"; }
std::string LidarMapper::occupiedTopic() const { return "robots/" + robot_id_ + "/map/occupied"; }

std::string LidarMapper::poseTopic() const { return flight::poseEstimateTopic(robot_id_); }

void LidarMapper::onPose(const v1::PoseStamped& pose) {
  absl::MutexLock lock(&mutex_);
  const int64_t t = stampNs(pose.header());
  if (!poses_.empty() && t < stampNs(poses_.back().header())) poses_.clear();  // a reset
  poses_.push_back(pose);
  while (!poses_.empty() && stampNs(poses_.front().header()) < t - kPoseHistoryNs) {
    poses_.pop_front();
  }
  last_pose_arrival_ = std::chrono::steady_clock::now();
  ++poses_received_;  // a scan may be waiting for this pose (or the scans for poses)
}

void LidarMapper::onScan(const v1::LaserScan& scan) {
  {
    absl::MutexLock lock(&mutex_);
    ++stats_.scans_received;
    queue_.push_back(scan);
    while (queue_.size() > static_cast<size_t>(std::max(1, settings_.scan_queue_size))) {
      queue_.pop_front();
      ++stats_.scans_dropped;
    }
  }
}

std::optional<v1::PoseStamped> LidarMapper::poseAt(int64_t stamp_ns) const {
  std::optional<v1::PoseStamped> best;
  int64_t best_dt = 0;
  for (const auto& p : poses_) {
    const int64_t dt = std::abs(stampNs(p.header()) - stamp_ns);
    if (!best || dt < best_dt) {
      best = p;
      best_dt = dt;
    }
  }
  if (!best || static_cast<double>(best_dt) * 1e-9 > settings_.pose_match_s) return std::nullopt;
  return best;
}

void LidarMapper::run() {
  absl::MutexLock lock(&mutex_);
  while (true) {
    // Scans are followed while pose estimates arrive (host time: this is
    // about the data flowing, not about simulated time).
    const auto now = std::chrono::steady_clock::now();
    const bool posed = last_pose_arrival_ && now - *last_pose_arrival_ < kScanFollowAfterPose;
    if (posed != (scan_sub_ != nullptr)) {
      mutex_.Unlock();  // the scan callback takes mutex_
      followScans(posed);
      mutex_.Lock();
      continue;
    }
    const uint64_t poses_seen = poses_received_;
    if (posed) {
      const auto scan_or_stop = [this]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
        return stopping_ || !queue_.empty();
      };
      mutex_.AwaitWithTimeout(absl::Condition(&scan_or_stop),
                              absl::FromChrono(*last_pose_arrival_ + kScanFollowAfterPose - now));
    } else {
      const auto scan_pose_or_stop = [this, poses_seen]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
        return stopping_ || !queue_.empty() || poses_received_ != poses_seen;
      };
      mutex_.Await(absl::Condition(&scan_pose_or_stop));
    }
    if (stopping_) return;
    if (queue_.empty()) continue;
    v1::LaserScan scan = std::move(queue_.front());
    queue_.pop_front();
    const int64_t stamp = stampNs(scan.header());
    std::optional<v1::PoseStamped> pose = poseAt(stamp);
    // The pose of a fresh scan may still be on its way (the newest pose is
    // older than the scan): wait a little. Otherwise, with no pose estimate
    // at all or only newer ones, none will come: skip at once, or a backlog
    // of scans taken before localization started (10 Hz at a 5x time scale
    // is 50 a second) would hold the mapping thread for seconds each.
    if (!pose && !poses_.empty() && stampNs(poses_.back().header()) < stamp &&
        stamp - stampNs(poses_.back().header()) < kPoseWaitWindowNs) {
      waiting_for_pose_ = true;  // caught up: the pose comes with later data
      const auto posed_or_stop = [this, stamp]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
        return stopping_ || (!poses_.empty() && stampNs(poses_.back().header()) >= stamp);
      };
      mutex_.AwaitWithTimeout(absl::Condition(&posed_or_stop), absl::Milliseconds(50));
      waiting_for_pose_ = false;
      if (stopping_) return;
      pose = poseAt(stamp);
    }
    if (!pose) {
      ++stats_.scans_without_pose;
      continue;
    }
    if (pose->has_horizontal_stddev_m() &&
        !(pose->horizontal_stddev_m() <= settings_.max_pose_stddev_m)) {
      ++stats_.scans_uncertain;
      continue;
    }
    if (!thinner_.admit(stamp, vec(pose->pose().position_m()), quat(pose->pose().orientation()))) {
      ++stats_.scans_thinned;
      continue;
    }
    inserting_ = true;
    mutex_.Unlock();
    insert(scan, *pose);
    mutex_.Lock();
    inserting_ = false;
    ++stats_.scans_inserted;
  }
}

bool LidarMapper::caughtUp() const {
  absl::MutexLock lock(&mutex_);
  return !inserting_ && (queue_.empty() || waiting_for_pose_);
}

void LidarMapper::insert(const v1::LaserScan& scan, const v1::PoseStamped& pose) {
  const Eigen::Quaterniond q = quat(pose.pose().orientation());
  const Eigen::Vector3d body = vec(pose.pose().position_m());
  const Eigen::Vector3d origin = body + q * settings_.lidar_mount_m;
  if (!origin.allFinite()) return;
  const double max_range = std::min(settings_.max_range_m, scan.range_max_m());
  std::vector<Eigen::Vector3d> hits, misses;
  hits.reserve(static_cast<size_t>(scan.ranges_m_size()));
  for (int i = 0; i < scan.ranges_m_size(); ++i) {
    const double r = scan.ranges_m(i);
    if (std::isnan(r) || r < scan.range_min_m()) continue;
    const double a = scan.angle_min_rad() + i * scan.angle_increment_rad();
    const Eigen::Vector3d dir = q * Eigen::Vector3d(std::cos(a), std::sin(a), 0.0);
    if (std::isinf(r) || r > max_range) {
      misses.push_back(origin + dir * max_range);
      continue;
    }
    const Eigen::Vector3d hit = origin + dir * (r + settings_.hit_depth_m);
    if (settings_.ground.mayBeGround(hit.z(), dir.z(), r)) continue;  // seen tilted
    hits.push_back(hit);
  }
  {
    absl::MutexLock lock(&map_mutex_);
    map_.insertScan(origin, hits, misses);
    columns_.afterScan(map_, hits);
  }
  publishOccupied(scan, origin.z());
}

void LidarMapper::publishOccupied(const v1::LaserScan& scan, double height_m) {
  constexpr int64_t kPeriodNs = 1'000'000'000;
  const int64_t stamp = stampNs(scan.header());
  const auto now = std::chrono::steady_clock::now();
  if (channel_ == nullptr || stamp - occupied_published_stamp_ns_ < kPeriodNs ||
      now - occupied_published_at_ < std::chrono::nanoseconds(kPeriodNs)) {
    return;
  }
  v1::PointCloud cloud;
  {
    absl::MutexLock lock(&map_mutex_);
    if (map_.revision() == occupied_published_revision_) return;
    occupied_published_revision_ = map_.revision();
    const octomap::OcTree& tree = map_.tree();
    const double half = tree.getResolution() / 2.0;
    for (auto it = tree.begin_leafs(); it != tree.end_leafs(); ++it) {
      if (!tree.isNodeOccupied(*it)) continue;
      // A pruned leaf is a cube of several voxels: its centre stands for it.
      const double reach = it.getSize() / 2.0 + half;
      if (std::abs(it.getZ() - height_m) > reach) continue;
      auto* point = cloud.add_points_m();
      point->set_x(it.getX());
      point->set_y(it.getY());
      point->set_z(it.getZ());
    }
  }
  *cloud.mutable_header() = scan.header();
  cloud.mutable_header()->set_frame_id("world");
  occupied_published_stamp_ns_ = stamp;
  occupied_published_at_ = now;
  (void)channel_->publish(occupiedTopic(), cloud);  // for display only
}

void LidarMapper::clear() {
  {
    absl::MutexLock lock(&map_mutex_);
    map_.clear();
    columns_.clear();
  }
  // Then the next scan is mapped whatever it is (reset before the map was
  // cleared, a scan mapped in between would be lost and the next thinned).
  absl::MutexLock lock(&mutex_);
  thinner_.reset();
}

std::optional<v1::PoseStamped> LidarMapper::latestPose() const {
  absl::MutexLock lock(&mutex_);
  if (poses_.empty()) return std::nullopt;
  return poses_.back();
}

MapperStats LidarMapper::stats() const {
  absl::MutexLock lock(&mutex_);
  return stats_;
}

std::optional<std::pair<Eigen::Vector3d, Eigen::Vector3d>> LidarMapper::planningVolumeLocked(
    const OccupancyMap& map) const {
  const octomap::OcTree& tree = map.tree();
  if (tree.size() == 0) return std::nullopt;
  double x0, y0, z0, x1, y1, z1;
  tree.getMetricMin(x0, y0, z0);
  tree.getMetricMax(x1, y1, z1);
  return std::pair{Eigen::Vector3d(x0, y0, settings_.planning_min_z_m),
                   Eigen::Vector3d(x1, y1, settings_.planning_max_z_m)};
}

}  // namespace behaviorlib::nav
