#pragma once

// Samples read from a Prometheus text exposition (a scraped /metrics page),
// for integration tests that check what a real server process exposes.
// prometheus-cpp writes the format but has no reader.

#include <cstdlib>
#include <map>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

namespace support {

using MetricLabels = std::map<std::string, std::string>;

/// The values of the samples of `name` whose labels include `labels`, in
/// page order. Label values are taken as written (our label values hold no
/// escaped quotes or commas).
inline std::vector<double> metricSamples(const std::string& text, const std::string& name,
                                         const MetricLabels& labels = {}) {
  std::vector<double> out;
  std::istringstream lines(text);
  for (std::string line; std::getline(lines, line);) {
    if (line.empty() || line[0] == '#') continue;
    const size_t end_of_name = line.find_first_of("{ ");
    if (end_of_name == std::string::npos || line.compare(0, end_of_name, name) != 0 ||
        end_of_name != name.size()) {
      continue;
    }
    MetricLabels found;
    size_t rest = end_of_name;
    if (line[end_of_name] == '{') {
      const size_t close = line.find('}', end_of_name);
      if (close == std::string::npos) continue;
      std::istringstream pairs(line.substr(end_of_name + 1, close - end_of_name - 1));
      for (std::string pair; std::getline(pairs, pair, ',');) {
        const size_t eq = pair.find('=');
        if (eq == std::string::npos || pair.size() < eq + 3) continue;
        found[pair.substr(0, eq)] = pair.substr(eq + 2, pair.size() - eq - 3);  // unquoted
      }
      rest = close + 1;
    }
    bool match = true;
    for (const auto& [key, wanted] : labels) {
      auto it = found.find(key);
      match = match && it != found.end() && it->second == wanted;
    }
    if (match) out.push_back(std::strtod(line.c_str() + rest, nullptr));
  }
  return out;
}

/// The first such sample's value; nullopt when there is none.
inline std::optional<double> metricValue(const std::string& text, const std::string& name,
                                         const MetricLabels& labels = {}) {
  const std::vector<double> samples = metricSamples(text, name, labels);
  if (samples.empty()) return std::nullopt;
  return samples.front();
}

/// The sum of such samples (0 when there is none).
inline double metricSum(const std::string& text, const std::string& name,
                        const MetricLabels& labels = {}) {
  double sum = 0;
  for (double v : metricSamples(text, name, labels)) sum += v;
  return sum;
}

}  // namespace support
