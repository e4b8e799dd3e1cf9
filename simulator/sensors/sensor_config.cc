// loadSensorConfig()/parseSensorConfig(): the YAML sensor-configuration
// reader. Every problem is reported as "<file>:<line>: <section>: <problem>"
// using yaml-cpp's marks, as world files are (formats/world/world_file.cc).

#include "simulator/sensors/sensor_config.h"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <map>
#include <optional>
#include <set>
#include <sstream>
#include <vector>

#include "behaviorlib/server_kit/confined_files.h"
#include "behaviorlib/server_kit/yaml_guard.h"
#include "formats/world/str_cat.h"

namespace behaviorlib::sim {
namespace {

using world::internal::strCat;

/// One setting that is wrong, and where (for the line number in files).
struct Problem {
  std::string section;  ///< "imu", "lidar", ... or "" for the top level
  std::string key;      ///< the offending key, or "" for the whole section
  std::string message;  ///< what is wrong, naming the key
};

constexpr double kMaxRateHz = 1000.0;  // the physics rate: no faster sampling

std::optional<Problem> checkRate(std::string_view section, std::string_view key, double rate) {
  if (!(rate >= 0.0 && rate <= kMaxRateHz)) {
    return Problem{
        std::string(section), std::string(key),
        strCat(key, " must be within [0, ", kMaxRateHz, "] (0 disables it), got ", rate)};
  }
  return std::nullopt;
}

std::optional<Problem> checkNonNegative(std::string_view section, std::string_view key,
                                        double value) {
  if (!(value >= 0.0) || !std::isfinite(value)) {
    return Problem{std::string(section), std::string(key),
                   strCat(key, " must be a non-negative number, got ", value)};
  }
  return std::nullopt;
}

std::optional<Problem> findProblem(const SensorConfig& c) {
  std::vector<std::optional<Problem>> checks = {
      checkRate("imu", "rate_hz", c.imu.rate_hz),
      checkNonNegative("imu", "gyro_noise_stddev_rad_s", c.imu.gyro_noise_stddev_rad_s),
      checkNonNegative("imu", "gyro_bias_stddev_rad_s", c.imu.gyro_bias_stddev_rad_s),
      checkNonNegative("imu", "gyro_bias_walk_rad_s_sqrt_s", c.imu.gyro_bias_walk_rad_s_sqrt_s),
      checkNonNegative("imu", "accel_noise_stddev_m_s2", c.imu.accel_noise_stddev_m_s2),
      checkNonNegative("imu", "accel_bias_stddev_m_s2", c.imu.accel_bias_stddev_m_s2),
      checkNonNegative("imu", "accel_bias_walk_m_s2_sqrt_s", c.imu.accel_bias_walk_m_s2_sqrt_s),
      checkNonNegative("imu", "orientation_noise_stddev_rad", c.imu.orientation_noise_stddev_rad),
      checkRate("gps", "rate_hz", c.gps.rate_hz),
      checkNonNegative("gps", "horizontal_stddev_m", c.gps.horizontal_stddev_m),
      checkNonNegative("gps", "vertical_stddev_m", c.gps.vertical_stddev_m),
      checkRate("baro", "rate_hz", c.baro.rate_hz),
      checkNonNegative("baro", "noise_stddev_m", c.baro.noise_stddev_m),
      checkNonNegative("baro", "drift_walk_m_sqrt_s", c.baro.drift_walk_m_sqrt_s),
      checkRate("linear_speed", "rate_hz", c.linear_speed.rate_hz),
      checkNonNegative("linear_speed", "noise_stddev_m_s", c.linear_speed.noise_stddev_m_s),
      checkRate("battery", "rate_hz", c.battery.rate_hz),
      checkNonNegative("battery", "voltage_noise_stddev_v", c.battery.voltage_noise_stddev_v),
      checkNonNegative("battery", "current_noise_stddev_a", c.battery.current_noise_stddev_a),
      checkRate("lidar", "rate_hz", c.lidar.rate_hz),
      checkNonNegative("lidar", "noise_stddev_m", c.lidar.noise_stddev_m),
      checkRate("camera", "rate_hz", c.camera.rate_hz),
      checkRate("camera", "info_rate_hz", c.camera.info_rate_hz),
  };
  for (auto& check : checks) {
    if (check) return check;
  }
  const LidarSensorConfig& l = c.lidar;
  auto lidar = [](std::string key, std::string message) {
    return Problem{"lidar", std::move(key), std::move(message)};
  };
  if (l.beams < 1 || l.beams > 100000) return lidar("beams", "beams must be within 1..100000");
  if (l.channels < 1 || l.channels > 1024) {
    return lidar("channels", "channels must be within 1..1024");
  }
  if (static_cast<long>(l.beams) * l.channels > 1000000) {
    return lidar("channels", "beams x channels must be at most 1000000");
  }
  if (!(l.field_of_view_rad > 0.0 && l.field_of_view_rad <= 2.0 * std::numbers::pi + 1e-9)) {
    return lidar("field_of_view_rad", "field_of_view_rad must be within (0, 2 pi]");
  }
  if (l.threeD()) {
    if (!(l.elevation_min_rad >= -std::numbers::pi / 2 &&
          l.elevation_max_rad <= std::numbers::pi / 2)) {
      return lidar("elevation_min_rad", "elevations must be within [-pi/2, pi/2]");
    }
    if (!(l.elevation_max_rad >= l.elevation_min_rad)) {
      return lidar("elevation_max_rad", "elevation_max_rad must be >= elevation_min_rad");
    }
  }
  if (!(l.range_min_m >= 0.0)) return lidar("range_min_m", "range_min_m must be >= 0");
  if (!(l.range_max_m > l.range_min_m) || !std::isfinite(l.range_max_m)) {
    return lidar("range_max_m", "range_max_m must be a number > range_min_m");
  }
  if (!l.mount_position_m.allFinite()) {
    return lidar("mount_position_m", "mount_position_m must be finite");
  }
  const CameraSensorConfig& cam = c.camera;
  auto camera = [](std::string key, std::string message) {
    return Problem{"camera", std::move(key), std::move(message)};
  };
  if (cam.width_px < 8 || cam.width_px > 8192) {
    return camera("width_px", "width_px must be within 8..8192");
  }
  if (cam.height_px < 8 || cam.height_px > 8192) {
    return camera("height_px", "height_px must be within 8..8192");
  }
  if (!(cam.horizontal_fov_rad > 0.0 &&
        cam.horizontal_fov_rad < 175.0 * std::numbers::pi / 180.0)) {
    return camera("horizontal_fov_rad", "horizontal_fov_rad must be within (0, 175 degrees)");
  }
  if (!cam.mount_position_m.allFinite()) {
    return camera("mount_position_m", "mount_position_m must be finite");
  }
  if (!std::isfinite(cam.mount_pitch_rad)) {
    return camera("mount_pitch_rad", "mount_pitch_rad must be finite");
  }
  if (cam.format != "jpeg" && cam.format != "png") {
    return camera("format", strCat("format must be jpeg or png, got '", cam.format, "'"));
  }
  if (cam.jpeg_quality < 1 || cam.jpeg_quality > 100) {
    return camera("jpeg_quality", "jpeg_quality must be within 1..100");
  }
  if (c.worker_threads < 1 || c.worker_threads > 16) {
    return Problem{"", "worker_threads", "worker_threads must be within 1..16"};
  }
  return std::nullopt;
}

std::string format(const Problem& p) {
  return p.section.empty() ? p.message : strCat(p.section, ": ", p.message);
}

int lineOf(const YAML::Node& node) {
  const YAML::Mark mark = node.Mark();
  return mark.is_null() ? 1 : mark.line + 1;
}

/// One key of a section and where its value goes.
struct Field {
  enum class Type { kNumber, kInteger, kVector3, kString };
  std::string_view key;
  Type type;
  void* out;
};

Field number(std::string_view key, double* out) { return {key, Field::Type::kNumber, out}; }
Field integer(std::string_view key, int* out) { return {key, Field::Type::kInteger, out}; }
Field vector3(std::string_view key, Eigen::Vector3d* out) {
  return {key, Field::Type::kVector3, out};
}
Field text(std::string_view key, std::string* out) { return {key, Field::Type::kString, out}; }

class Parser {
 public:
  explicit Parser(std::string source) : source_(std::move(source)) {}

  absl::Status errorAtLine(int line, std::string_view what, std::string_view problem) const {
    if (what.empty()) return absl::InvalidArgumentError(strCat(source_, ":", line, ": ", problem));
    return absl::InvalidArgumentError(strCat(source_, ":", line, ": ", what, ": ", problem));
  }
  absl::Status error(const YAML::Node& at, std::string_view what, std::string_view problem) const {
    return errorAtLine(lineOf(at), what, problem);
  }

  /// Reads the mapping `node` (section `what`, "" for the top level) into
  /// `fields`; keys in `sections` are left for the caller. Records the line
  /// of every key for later messages.
  absl::Status section(const YAML::Node& node, std::string_view what,
                       const std::vector<Field>& fields,
                       const std::vector<std::string_view>& sections = {}) {
    if (!node.IsMap()) {
      return error(node, what, "must be a mapping of keys to values");
    }
    lines_[std::string(what)][""] = lineOf(node);
    std::set<std::string> seen;
    for (const auto& entry : node) {
      const YAML::Node& key = entry.first;
      if (!key.IsScalar()) return error(key, what, "keys must be plain names");
      const std::string name = key.Scalar();
      if (!seen.insert(name).second) return error(key, what, strCat("duplicate key '", name, "'"));
      lines_[std::string(what)][name] = lineOf(key);
      if (std::find(sections.begin(), sections.end(), name) != sections.end()) continue;
      const auto field =
          std::find_if(fields.begin(), fields.end(), [&](const Field& f) { return f.key == name; });
      if (field == fields.end()) {
        std::string allowed;
        for (const Field& f : fields) allowed += strCat(allowed.empty() ? "" : ", ", f.key);
        for (std::string_view s : sections) allowed += strCat(allowed.empty() ? "" : ", ", s);
        return error(key, what, strCat("unknown key '", name, "' (allowed: ", allowed, ")"));
      }
      if (absl::Status s = read(entry.second, what, *field); !s.ok()) return s;
    }
    return absl::OkStatus();
  }

  /// The line of `key` in `section` (or of the section, or 1).
  int lineFor(const std::string& section, const std::string& key) const {
    auto s = lines_.find(section);
    if (s == lines_.end()) return 1;
    if (auto k = s->second.find(key); k != s->second.end()) return k->second;
    if (auto whole = s->second.find(""); whole != s->second.end()) return whole->second;
    return 1;
  }

 private:
  absl::Status read(const YAML::Node& value, std::string_view what, const Field& field) const {
    switch (field.type) {
      case Field::Type::kNumber: {
        double number = 0.0;
        if (!value.IsScalar() || !YAML::convert<double>::decode(value, number) ||
            !std::isfinite(number)) {
          return error(value, what, strCat(field.key, " must be a number"));
        }
        *static_cast<double*>(field.out) = number;
        return absl::OkStatus();
      }
      case Field::Type::kInteger: {
        int number = 0;
        if (!value.IsScalar() || !YAML::convert<int>::decode(value, number)) {
          return error(value, what, strCat(field.key, " must be an integer"));
        }
        *static_cast<int*>(field.out) = number;
        return absl::OkStatus();
      }
      case Field::Type::kVector3: {
        const absl::Status bad =
            error(value, what, strCat(field.key, " must be a list of 3 numbers [x, y, z]"));
        if (!value.IsSequence() || value.size() != 3) return bad;
        Eigen::Vector3d v;
        for (int i = 0; i < 3; ++i) {
          if (!value[i].IsScalar() || !YAML::convert<double>::decode(value[i], v[i]) ||
              !std::isfinite(v[i])) {
            return bad;
          }
        }
        *static_cast<Eigen::Vector3d*>(field.out) = v;
        return absl::OkStatus();
      }
      case Field::Type::kString:
        if (!value.IsScalar()) return error(value, what, strCat(field.key, " must be a string"));
        *static_cast<std::string*>(field.out) = value.Scalar();
        return absl::OkStatus();
    }
    return absl::OkStatus();
  }

  std::string source_;
  std::map<std::string, std::map<std::string, int>> lines_;  // section -> key -> line
};

absl::Status parseRoot(Parser& parser, const YAML::Node& root, SensorConfig* c) {
  // An empty file (or one with only comments) keeps every default.
  if (!root || root.IsNull()) return absl::OkStatus();
  const std::vector<std::string_view> sections = {"imu",     "gps",   "baro",  "linear_speed",
                                                  "battery", "lidar", "camera"};
  if (absl::Status s =
          parser.section(root, "", {integer("worker_threads", &c->worker_threads)}, sections);
      !s.ok()) {
    return s;
  }
  const std::map<std::string_view, std::vector<Field>> fields = {
      {"imu",
       {number("rate_hz", &c->imu.rate_hz),
        number("gyro_noise_stddev_rad_s", &c->imu.gyro_noise_stddev_rad_s),
        number("gyro_bias_stddev_rad_s", &c->imu.gyro_bias_stddev_rad_s),
        number("gyro_bias_walk_rad_s_sqrt_s", &c->imu.gyro_bias_walk_rad_s_sqrt_s),
        number("accel_noise_stddev_m_s2", &c->imu.accel_noise_stddev_m_s2),
        number("accel_bias_stddev_m_s2", &c->imu.accel_bias_stddev_m_s2),
        number("accel_bias_walk_m_s2_sqrt_s", &c->imu.accel_bias_walk_m_s2_sqrt_s),
        number("orientation_noise_stddev_rad", &c->imu.orientation_noise_stddev_rad)}},
      {"gps",
       {number("rate_hz", &c->gps.rate_hz),
        number("horizontal_stddev_m", &c->gps.horizontal_stddev_m),
        number("vertical_stddev_m", &c->gps.vertical_stddev_m)}},
      {"baro",
       {number("rate_hz", &c->baro.rate_hz), number("noise_stddev_m", &c->baro.noise_stddev_m),
        number("drift_walk_m_sqrt_s", &c->baro.drift_walk_m_sqrt_s)}},
      {"linear_speed",
       {number("rate_hz", &c->linear_speed.rate_hz),
        number("noise_stddev_m_s", &c->linear_speed.noise_stddev_m_s)}},
      {"battery",
       {number("rate_hz", &c->battery.rate_hz),
        number("voltage_noise_stddev_v", &c->battery.voltage_noise_stddev_v),
        number("current_noise_stddev_a", &c->battery.current_noise_stddev_a)}},
      {"lidar",
       {number("rate_hz", &c->lidar.rate_hz), integer("beams", &c->lidar.beams),
        number("field_of_view_rad", &c->lidar.field_of_view_rad),
        integer("channels", &c->lidar.channels),
        number("elevation_min_rad", &c->lidar.elevation_min_rad),
        number("elevation_max_rad", &c->lidar.elevation_max_rad),
        number("range_min_m", &c->lidar.range_min_m), number("range_max_m", &c->lidar.range_max_m),
        number("noise_stddev_m", &c->lidar.noise_stddev_m),
        vector3("mount_position_m", &c->lidar.mount_position_m)}},
      {"camera",
       {number("rate_hz", &c->camera.rate_hz), number("info_rate_hz", &c->camera.info_rate_hz),
        integer("width_px", &c->camera.width_px), integer("height_px", &c->camera.height_px),
        number("horizontal_fov_rad", &c->camera.horizontal_fov_rad),
        vector3("mount_position_m", &c->camera.mount_position_m),
        number("mount_pitch_rad", &c->camera.mount_pitch_rad), text("format", &c->camera.format),
        integer("jpeg_quality", &c->camera.jpeg_quality)}},
  };
  for (std::string_view name : sections) {
    const YAML::Node node = root[std::string(name)];
    if (!node || node.IsNull()) continue;  // "imu:" with nothing under it: defaults
    if (absl::Status s = parser.section(node, name, fields.at(name)); !s.ok()) return s;
  }
  if (std::optional<Problem> problem = findProblem(*c)) {
    return parser.errorAtLine(parser.lineFor(problem->section, problem->key), problem->section,
                              problem->message);
  }
  return absl::OkStatus();
}

}  // namespace

LidarConfig LidarSensorConfig::lidarConfig() const {
  LidarConfig config;
  config.beams = beams;
  config.angle_min_rad = -field_of_view_rad / 2.0;
  config.angle_max_rad = field_of_view_rad / 2.0;
  config.channels = channels;
  config.elevation_min_rad = threeD() ? elevation_min_rad : 0.0;
  config.elevation_max_rad = threeD() ? elevation_max_rad : 0.0;
  config.range_min_m = range_min_m;
  config.range_max_m = range_max_m;
  config.noise_stddev_m = noise_stddev_m;
  config.mount_position_m = mount_position_m;
  return config;
}

CameraConfig CameraSensorConfig::cameraConfig() const {
  CameraConfig config;
  config.width_px = width_px;
  config.height_px = height_px;
  config.horizontal_fov_rad = horizontal_fov_rad;
  config.mount_position_m = mount_position_m;
  config.mount_pitch_rad = mount_pitch_rad;
  return config;
}

absl::Status SensorConfig::validate() const {
  if (std::optional<Problem> problem = findProblem(*this)) {
    return absl::InvalidArgumentError(format(*problem));
  }
  return absl::OkStatus();
}

absl::StatusOr<SensorConfig> parseSensorConfig(std::string_view yaml_text,
                                               std::string_view source_name) {
  Parser parser{std::string(source_name)};
  SensorConfig config;
  YAML::Node root;
  if (absl::Status s = server_kit::loadYaml(yaml_text, std::string(source_name), &root); !s.ok()) {
    return s;
  }
  if (absl::Status s = server_kit::guardYamlParse(std::string(source_name),
                                                  [&] { return parseRoot(parser, root, &config); });
      !s.ok()) {
    return s;
  }
  return config;
}

absl::StatusOr<SensorConfig> loadSensorConfig(const std::string& path) {
  absl::StatusOr<std::string> content = server_kit::readFileCapped(path, 1 << 20);
  if (!content.ok()) return content.status();
  return parseSensorConfig(*content, path);
}

}  // namespace behaviorlib::sim
