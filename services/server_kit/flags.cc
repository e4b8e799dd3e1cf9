#include "behaviorlib/server_kit/flags.h"

#include <charconv>
#include <cstdio>
#include <cstdlib>
#include <sstream>

namespace behaviorlib::server {

FlagSet::FlagSet(std::string program_description) : description_(std::move(program_description)) {}

void FlagSet::add(std::string name, std::string* value, std::string help) {
  flags_.push_back({std::move(name), std::move(help), *value,
                    [value](const std::string& v) {
                      *value = v;
                      return true;
                    },
                    false});
}

void FlagSet::add(std::string name, double* value, std::string help) {
  std::ostringstream def;
  def << *value;
  flags_.push_back({std::move(name), std::move(help), def.str(),
                    [value](const std::string& v) {
                      char* end = nullptr;
                      double d = std::strtod(v.c_str(), &end);
                      if (v.empty() || *end != '\0') return false;
                      *value = d;
                      return true;
                    },
                    false});
}

void FlagSet::add(std::string name, int* value, std::string help) {
  flags_.push_back({std::move(name), std::move(help), std::to_string(*value),
                    [value](const std::string& v) {
                      int n = 0;
                      const char* end = v.data() + v.size();
                      const auto [at, ec] = std::from_chars(v.data(), end, n);
                      if (v.empty() || ec != std::errc() || at != end) return false;
                      *value = n;
                      return true;
                    },
                    false});
}

void FlagSet::add(std::string name, bool* value, std::string help) {
  flags_.push_back({std::move(name), std::move(help), *value ? "true" : "false",
                    [value](const std::string& v) {
                      if (v == "true" || v == "1" || v.empty()) {
                        *value = true;
                      } else if (v == "false" || v == "0") {
                        *value = false;
                      } else {
                        return false;
                      }
                      return true;
                    },
                    true});
}

std::string FlagSet::usage(const std::string& program) const {
  std::ostringstream out;
  out << program << ": " << description_ << "\n\nFlags:\n";
  for (const auto& f : flags_) {
    out << "  --" << f.name << (f.is_bool ? "" : " VALUE") << "\n      " << f.help;
    if (!f.default_text.empty()) out << " (default: " << f.default_text << ")";
    out << "\n";
  }
  return out.str();
}

bool FlagSet::parse(int argc, char** argv, int* exit_code) {
  const std::string program = argc > 0 ? argv[0] : "program";
  auto fail = [&](const std::string& message) {
    std::fprintf(stderr, "%s: %s\nRun with --help for the list of flags.\n", program.c_str(),
                 message.c_str());
    if (exit_code) *exit_code = 2;
    return false;
  };
  for (int i = 1; i < argc; ++i) {
    std::string arg = argv[i];
    if (arg == "--help" || arg == "-h") {
      std::fputs(usage(program).c_str(), stdout);
      if (exit_code) *exit_code = 0;
      return false;
    }
    if (arg.rfind("--", 0) != 0) return fail("unexpected argument '" + arg + "'");
    std::string name = arg.substr(2);
    std::string value;
    bool has_value = false;
    if (auto eq = name.find('='); eq != std::string::npos) {
      value = name.substr(eq + 1);
      name = name.substr(0, eq);
      has_value = true;
    }
    const Flag* flag = nullptr;
    for (const auto& f : flags_) {
      if (f.name == name) flag = &f;
    }
    if (!flag) return fail("unknown flag --" + name);
    if (!has_value && !flag->is_bool) {
      if (i + 1 >= argc) return fail("flag --" + name + " needs a value");
      value = argv[++i];
    }
    if (!flag->set(value)) return fail("bad value '" + value + "' for --" + name);
  }
  return true;
}

}  // namespace behaviorlib::server
