#include "simulator/sensors/sensor_system.h"

#include <cmath>
#include <limits>
#include <opencv2/core.hpp>
#include <stdexcept>

namespace behaviorlib::sim {
namespace {

std::size_t indexOf(SensorKind kind) { return static_cast<std::size_t>(kind); }

SensorConfig validated(SensorConfig config) {
  if (absl::Status status = config.validate(); !status.ok()) {
    throw std::invalid_argument("SensorSystem: " + std::string(status.message()));
  }
  return config;
}

LidarData lidarData(const Lidar& lidar, const LidarScan& scan, bool three_d) {
  LidarData data;
  const LidarConfig& c = lidar.config();
  data.three_d = three_d;
  data.range_min_m = c.range_min_m;
  data.range_max_m = c.range_max_m;
  data.angle_min_rad = lidar.azimuthRad(0);
  data.angle_max_rad = lidar.azimuthRad(c.beams - 1);
  data.angle_increment_rad = c.beams > 1 ? lidar.azimuthRad(1) - lidar.azimuthRad(0) : 0.0;
  if (!three_d) {
    data.ranges_m = scan.ranges_m;
    return data;
  }
  data.points_m.reserve(scan.ranges_m.size());
  for (int channel = 0; channel < scan.channels; ++channel) {
    for (int beam = 0; beam < scan.beams; ++beam) {
      const float range = scan.at(channel, beam);
      if (!std::isfinite(range)) continue;  // nothing hit, or too close
      data.points_m.push_back((lidar.direction(channel, beam) * range).cast<float>());
    }
  }
  return data;
}

}  // namespace

SensorSystem::SensorSystem(SensorConfig config, Sink sink, FrameTimer frame_timer)
    : config_(validated(std::move(config))),
      user_sink_(std::move(sink)),
      sink_([this](SensorSample sample) {
        published_[indexOf(sample.kind)].fetch_add(1, std::memory_order_relaxed);
        user_sink_(std::move(sample));
      }),
      frame_timer_(std::move(frame_timer)),
      scene_(std::make_shared<const SensorScene>(nullptr, config_)),
      workers_(config_.worker_threads) {}

SensorSystem::~SensorSystem() { workers_.stop(); }

void SensorSystem::reset(std::shared_ptr<const world::World> world, uint64_t seed) {
  auto scene = std::make_shared<const SensorScene>(std::move(world), config_);
  {
    std::lock_guard lock(emit_mutex_);
    scene_->retired.store(true);
  }
  scene_ = std::move(scene);
  seed_ = seed;
  suites_.clear();
  std::lock_guard lock(channels_mutex_);
  for (auto& [id, channels] : channels_) {
    for (const auto& channel : channels) channel->clearFaults();
  }
}

const SensorChannels& SensorSystem::channelsOf(const std::string& robot_id) {
  std::lock_guard lock(channels_mutex_);
  auto it = channels_.find(robot_id);
  if (it == channels_.end()) {
    SensorChannels channels;
    for (auto& channel : channels) channel = std::make_shared<SensorChannel>();
    it = channels_.emplace(robot_id, std::move(channels)).first;
  }
  return it->second;  // std::map: stable, and entries are never erased
}

void SensorSystem::setFault(const std::string& robot_id, SensorKind kind, SimTime since,
                            const SensorFault& fault) {
  channelsOf(robot_id)[indexOf(kind)]->setFault(since, fault);
}

SensorFault SensorSystem::fault(const std::string& robot_id, SensorKind kind) const {
  std::lock_guard lock(channels_mutex_);
  auto it = channels_.find(robot_id);
  return it == channels_.end() ? SensorFault{} : it->second[indexOf(kind)]->current();
}

std::vector<SensorSystem::SensorStats> SensorSystem::stats() const {
  std::lock_guard lock(channels_mutex_);
  std::vector<SensorStats> out;
  for (const auto& [id, channels] : channels_) {
    for (int k = 0; k < kSensorKindCount; ++k) {
      const SensorChannel& channel = *channels[static_cast<std::size_t>(k)];
      SensorStats s;
      s.robot_id = id;
      s.kind = static_cast<SensorKind>(k);
      s.published = channel.published.load(std::memory_order_relaxed);
      s.fault_dropped = channel.fault_dropped.load(std::memory_order_relaxed);
      s.frames_dropped = channel.frames_dropped.load(std::memory_order_relaxed);
      s.fault = channel.current().type;
      out.push_back(std::move(s));
    }
  }
  return out;
}

void SensorSystem::onStep(SimTime now, const std::vector<VehicleReport>& vehicles,
                          bool wait_for_frames) {
  frames_.clear();
  for (const VehicleReport& report : vehicles) {
    auto it = suites_.find(*report.robot_id);
    if (it == suites_.end()) {
      it = suites_
               .emplace(*report.robot_id,
                        std::make_unique<SensorSuite>(*report.robot_id, config_, seed_, scene_,
                                                      &sink_, channelsOf(*report.robot_id)))
               .first;
    }
    it->second->step(now, report.snapshot, &frames_);
  }
  for (FrameRequest& request : frames_) {
    if (request.sensor->output.kind() == SensorKind::kCamera &&
        !cameraWanted(request.sensor->output.robotId())) {
      continue;  // nobody looks: neither rendered nor encoded
    }
    submit(std::move(request), wait_for_frames);
  }
  frames_.clear();
}

void SensorSystem::submit(FrameRequest request, bool wait) {
  FrameSensor& sensor = *request.sensor;
  const SensorKind kind = sensor.output.kind();
  // In lock-step a delayed frame must be in its output's queue before the
  // step it is due at, whatever the workers' speed: make it now.
  const bool delayed =
      wait && sensor.output.channel() != nullptr &&
      sensor.output.channel()->faultAt(request.stamp).type == SensorFaultType::kDelayed;
  auto job = [this, scene = scene_, request = std::move(request)] { makeFrame(scene, request); };
  if (workers_.submit(sensor.slot, std::move(job), wait)) {
    if (delayed) workers_.waitFor(sensor.slot);
  } else {
    dropped_[indexOf(kind)].fetch_add(1, std::memory_order_relaxed);
    if (SensorChannel* channel = sensor.output.channel()) {
      channel->frames_dropped.fetch_add(1, std::memory_order_relaxed);
    }
  }
}

void SensorSystem::makeFrame(const std::shared_ptr<const SensorScene>& scene,
                             const FrameRequest& request) {
  if (scene->retired.load()) return;
  FrameSensor& sensor = *request.sensor;
  const auto start = std::chrono::steady_clock::now();
  SampleData data;
  if (sensor.output.kind() == SensorKind::kLidar) {
    std::mt19937_64 rng(request.noise_seed);
    const LidarScan scan = scene->lidar->scan(request.position_m, request.orientation, rng);
    data = lidarData(*scene->lidar, scan, config_.lidar.threeD());
  } else {
    const cv::Mat image = scene->camera->render(request.position_m, request.orientation);
    absl::StatusOr<std::string> encoded =
        encodeImage(image, config_.camera.format, config_.camera.jpeg_quality);
    if (!encoded.ok()) {
      dropped_[indexOf(SensorKind::kCamera)].fetch_add(1, std::memory_order_relaxed);
      if (SensorChannel* channel = sensor.output.channel()) {
        channel->frames_dropped.fetch_add(1, std::memory_order_relaxed);
      }
      return;
    }
    CameraImageData frame;
    frame.width_px = image.cols;
    frame.height_px = image.rows;
    frame.encoding = config_.camera.format;
    frame.data = std::move(*encoded);
    data = std::move(frame);
  }
  if (frame_timer_) frame_timer_(sensor.output.kind(), std::chrono::steady_clock::now() - start);
  std::lock_guard lock(emit_mutex_);
  if (scene->retired.load()) return;
  sensor.output.publish(request.stamp, std::move(data));
}

void SensorSystem::setCameraWanted(const std::string& robot_id, bool wanted) {
  std::lock_guard lock(wanted_mutex_);
  if (wanted) {
    wanted_cameras_.insert(robot_id);
  } else {
    wanted_cameras_.erase(robot_id);
  }
}

void SensorSystem::setWantedCameras(std::set<std::string> robot_ids) {
  std::lock_guard lock(wanted_mutex_);
  wanted_cameras_ = std::move(robot_ids);
}

bool SensorSystem::cameraWanted(const std::string& robot_id) const {
  std::lock_guard lock(wanted_mutex_);
  return wanted_cameras_.count(robot_id) > 0;
}

uint64_t SensorSystem::publishedCount(SensorKind kind) const {
  return published_[indexOf(kind)].load();
}

uint64_t SensorSystem::droppedCount(SensorKind kind) const {
  return dropped_[indexOf(kind)].load();
}

void SensorSystem::waitIdle() { workers_.waitIdle(); }

}  // namespace behaviorlib::sim
