#pragma once

// LidarMapper: the OctoMap navigation_with_lidar keeps while it runs, built
// from the robot's lidar scans and its pose estimate, and shared by the
// system's behaviors.
//
//   LidarMapper mapper(channel, "drone1", settings);   // starts mapping
//   mapper.withMap([](const nav::OccupancyMap& map) { ... });  // locked
//   std::optional<v1::PoseStamped> pose = mapper.latestPose();
//
// Threads: the subscription's reader queues each scan (robots/{id}/lidar/scan,
// delivered in QUEUE mode: none is skipped by the broker) into a bounded
// local queue; a mapping thread of its own takes them in order and inserts
// them. A scan is placed with the pose estimate whose stamp is nearest to
// the scan's (robots/{id}/self_localization/pose, kept for the last second),
// and skipped when none is within pose_match_s, or when that estimate's
// horizontal_stddev_m exceeds max_pose_stddev_m.
//
// The lidar is 2-D (one horizontal plane). Rays are inserted as measured
// (hits, and free space along every ray); each voxel column where a hit
// lands is then marked occupied from column_min_z_m to column_max_z_m, so
// that a wall seen at flight height blocks the planner at every planned
// altitude (the building's walls are vertical; WallColumns). Hits that may
// be the ground, seen by a tilted vehicle, are ignored (GroundRejection: at
// or below ground_max_z_m, or on a surely descending ray within the pose
// estimate's altitude and attitude errors of it). A hit is
// placed hit_depth_m behind the measured range, inside the surface: a
// surface on a voxel boundary (every wall of a building drawn on a 0.1 m
// grid) then maps into the obstacle's voxel, not, half the time by the range
// noise, into the free voxel beside it, which narrowed a door by a column
// for good. A surface inside a voxel moves by at most hit_depth_m.
//
// For operators (the console's map): after a scan goes in, at most once a
// second of scan time and of host time, the occupied voxels around the
// lidar's height are published on robots/{id}/map/occupied, a PointCloud of
// voxel centres (frame world; the map's resolution, 0.1 m by default).

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <deque>
#include <memory>
#include <optional>
#include <string>
#include <thread>

#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/config/v1/navigation_with_lidar.pb.h"
#include "behaviorlib/navigation/ground_rejection.h"
#include "behaviorlib/navigation/occupancy_map.h"
#include "behaviorlib/navigation/scan_thinner.h"
#include "behaviorlib/navigation/wall_columns.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::nav {

/// The `mapping:` section of the system's --config. Its keys, their ranges
/// and defaults are declared in proto/behaviorlib/config/v1/
/// navigation_with_lidar.proto (MappingConfig); the defaults here are the
/// same.
struct MapperSettings {
  double resolution_m = 0.1;
  /// Ranges beyond this are inserted as free space up to it only.
  double max_range_m = 12.0;
  /// Lidar position in the body frame (the simulator's default mount).
  Eigen::Vector3d lidar_mount_m{0.0, 0.0, 0.1};
  /// Which hits are the ground seen by a tilted vehicle (dropped): keys
  /// ground_max_z_m, ground_altitude_error_m, ground_attitude_error_rad
  /// (navigation/ground_rejection.h).
  GroundRejection ground;
  /// How far behind the measured range a hit is placed (a few times the
  /// lidar's range noise, 0.01 m in the simulator).
  double hit_depth_m = 0.03;
  double column_min_z_m = 0.0;
  double column_max_z_m = 3.0;
  /// Altitudes a path may use; a goal outside them is outside the map. A
  /// 2-D lidar cannot see what lies above a door (its lintel, 2.2 m up in
  /// the building): the top stays below it by a vehicle radius (0.35 m) and
  /// 0.25 m for the estimated altitude's error (a barometer's: 0.2 m) and
  /// the tracking error.
  double planning_min_z_m = 0.5;
  double planning_max_z_m = 1.6;
  /// Largest stamp difference between a scan and the pose it is placed with.
  double pose_match_s = 0.05;
  /// A scan whose pose estimate reports a larger horizontal_stddev_m (a
  /// filter still converging after its start, a diverging one) is not
  /// mapped: its walls would land where they are not, and close doors.
  double max_pose_stddev_m = 0.15;
  /// Scans waiting for the mapping thread; the oldest is dropped beyond.
  int scan_queue_size = 50;
  /// Which scans are mapped (navigation/scan_thinner.h): at most one every
  /// min_interval_s of simulated time, and standing still (moved less than
  /// still_distance_m, turned less than still_angle_rad) one every
  /// still_interval_s. Keys min_scan_interval_s, still_distance_m,
  /// still_angle_rad, still_scan_interval_s.
  ScanThinningSettings thinning;

  /// Takes the decoded keys (defaults applied, ranges already checked) and
  /// checks the rules between them: lidar_mount_m has 3 numbers,
  /// planning_max_z_m above planning_min_z_m, column_max_z_m above
  /// column_min_z_m; INVALID_ARGUMENT naming the keys.
  absl::Status configure(const config::v1::MappingConfig& mapping);
};

/// Counters of the mapping thread.
struct MapperStats {
  uint64_t scans_received = 0;
  uint64_t scans_inserted = 0;
  uint64_t scans_without_pose = 0;
  uint64_t scans_dropped = 0;    ///< queue full
  uint64_t scans_thinned = 0;    ///< not needed (ScanThinner)
  uint64_t scans_uncertain = 0;  ///< pose estimate too uncertain (max_pose_stddev_m)
};

class LidarMapper {
 public:
  /// Subscribes and starts the mapping thread; `channel` may be null (no
  /// map is built then).
  LidarMapper(channel::ChannelClient* channel, std::string robot_id, MapperSettings settings);
  ~LidarMapper();
  LidarMapper(const LidarMapper&) = delete;
  LidarMapper& operator=(const LidarMapper&) = delete;

  const MapperSettings& settings() const { return settings_; }
  channel::ChannelClient* channel() const { return channel_; }
  const std::string& robotId() const { return robot_id_; }
  std::string scanTopic() const;
  std::string poseTopic() const;
  std::string occupiedTopic() const;

  /// Calls f(const OccupancyMap&) with the map locked (mapping waits).
  template <class F>
  auto withMap(F&& f) const {
    absl::MutexLock lock(&map_mutex_);
    return f(static_cast<const OccupancyMap&>(map_));
  }
  /// Forgets the map (and the extruded columns).
  void clear();
  /// The newest pose estimate received, if any.
  std::optional<v1::PoseStamped> latestPose() const;
  MapperStats stats() const;

  /// The box a plan may use: the horizontal extent of the known map and the
  /// planning altitudes; nullopt for an empty map. Map lock held by caller.
  std::optional<std::pair<Eigen::Vector3d, Eigen::Vector3d>> planningVolumeLocked(
      const OccupancyMap& map) const;

  /// Whether every scan received so far is in the map (or skipped), or the
  /// next waits for its pose estimate: the deterministic mode's catch-up
  /// check (BehaviorSystemBuilder::addCatchUpCheck).
  bool caughtUp() const;

 private:
  void onScan(const v1::LaserScan& scan);
  void onPose(const v1::PoseStamped& pose);
  void run();
  // Makes or drops the scan subscription (mapping thread only).
  void followScans(bool want);
  void insert(const v1::LaserScan& scan, const v1::PoseStamped& pose);
  // Publishes the occupied voxels at the lidar's height when due (mapping
  // thread only).
  void publishOccupied(const v1::LaserScan& scan, double height_m);
  std::optional<v1::PoseStamped> poseAt(int64_t stamp_ns) const
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);

  channel::ChannelClient* channel_;
  const std::string robot_id_;
  const MapperSettings settings_;

  mutable absl::Mutex map_mutex_;
  OccupancyMap map_ ABSL_GUARDED_BY(map_mutex_);
  WallColumns columns_ ABSL_GUARDED_BY(map_mutex_);

  // The queue, the poses and the statistics; the mapping thread waits on it
  // (Mutex::Await).
  mutable absl::Mutex mutex_;
  std::deque<v1::LaserScan> queue_ ABSL_GUARDED_BY(mutex_);
  std::deque<v1::PoseStamped> poses_ ABSL_GUARDED_BY(mutex_);  // the last second, by stamp
  MapperStats stats_ ABSL_GUARDED_BY(mutex_);
  ScanThinner thinner_ ABSL_GUARDED_BY(mutex_);
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  bool inserting_ ABSL_GUARDED_BY(mutex_) = false;  // a scan is going into the map
  // The next scan waits for its pose estimate.
  bool waiting_for_pose_ ABSL_GUARDED_BY(mutex_) = false;
  // When the last pose estimate arrived (host time); none yet: no scans.
  std::optional<std::chrono::steady_clock::time_point> last_pose_arrival_ ABSL_GUARDED_BY(mutex_);
  uint64_t poses_received_ ABSL_GUARDED_BY(mutex_) = 0;
  static constexpr std::chrono::seconds kScanFollowAfterPose{2};

  // The last publication of the occupied voxels (mapping thread only).
  int64_t occupied_published_stamp_ns_ = 0;
  std::chrono::steady_clock::time_point occupied_published_at_{};
  uint64_t occupied_published_revision_ ABSL_GUARDED_BY(map_mutex_) = 0;

  std::thread thread_;
  std::unique_ptr<channel::Subscription> scan_sub_, pose_sub_;
};

/// Nanoseconds of a header's stamp.
int64_t stampNs(const v1::Header& header);

}  // namespace behaviorlib::nav
