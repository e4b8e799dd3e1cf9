#include "behaviorlib/server_kit/yaml_guard.h"

#include <yaml-cpp/eventhandler.h>
#include <yaml-cpp/parser.h>

#include <algorithm>
#include <sstream>
#include <unordered_map>
#include <vector>

#include "absl/strings/str_cat.h"
#include "behaviorlib/error_details.h"

namespace behaviorlib::server_kit {
namespace {

// Thrown by the counting handler to stop the parser at the first limit passed.
struct LimitPassed {
  YAML::Mark mark;
  std::string what;
  std::string limit;  // the cap passed; empty for a refusal that is no cap
};

// Counts the document's nodes as if every alias were expanded. An anchored
// node's expanded size and depth are recorded when it ends, and an alias to
// it adds them.
class CountingHandler : public YAML::EventHandler {
 public:
  explicit CountingHandler(const YamlLimits& limits) : limits_(limits) {}

  void OnDocumentStart(const YAML::Mark&) override {}
  void OnDocumentEnd() override {}
  void OnNull(const YAML::Mark& mark, YAML::anchor_t anchor) override { leaf(mark, anchor); }
  void OnScalar(const YAML::Mark& mark, const std::string&, YAML::anchor_t anchor,
                const std::string&) override {
    leaf(mark, anchor);
  }
  void OnAlias(const YAML::Mark& mark, YAML::anchor_t anchor) override {
    if (++aliases_ > limits_.max_aliases) {
      throw LimitPassed{mark, absl::StrCat("more than ", limits_.max_aliases, " aliases"),
                        std::to_string(limits_.max_aliases)};
    }
    // An alias to a node still open refers to a node that contains it: the
    // tree yaml-cpp would build is a cycle, and whatever walks it recurses
    // without end (found by fuzz_catalog: `defaults: &d {x: *d}`).
    for (const Open& open : stack_) {
      if (open.anchor == anchor && anchor != YAML::NullAnchor) {
        throw LimitPassed{mark, "an alias inside the node it refers to (a cycle)", ""};
      }
    }
    const auto it = anchored_.find(anchor);
    // yaml-cpp refuses an alias to an unknown anchor itself.
    if (it == anchored_.end()) return;
    add(mark, it->second.nodes, it->second.depth);
  }
  void OnSequenceStart(const YAML::Mark& mark, const std::string&, YAML::anchor_t anchor,
                       YAML::EmitterStyle::value) override {
    open(mark, anchor);
  }
  void OnSequenceEnd() override { close(); }
  void OnMapStart(const YAML::Mark& mark, const std::string&, YAML::anchor_t anchor,
                  YAML::EmitterStyle::value) override {
    open(mark, anchor);
  }
  void OnMapEnd() override { close(); }

 private:
  struct Size {
    size_t nodes = 0;
    size_t depth = 0;  // levels below and including the node
  };
  struct Open {
    YAML::anchor_t anchor;
    size_t nodes_before;
    size_t deepest;  // deepest level reached inside, absolute
  };

  void leaf(const YAML::Mark& mark, YAML::anchor_t anchor) {
    add(mark, 1, 1);
    if (anchor != YAML::NullAnchor) anchored_[anchor] = Size{1, 1};
  }
  // `nodes` more nodes reaching `depth` levels below the current one.
  void add(const YAML::Mark& mark, size_t nodes, size_t depth) {
    nodes_ += nodes;
    if (nodes_ > limits_.max_nodes) {
      throw LimitPassed{
          mark,
          absl::StrCat("more than ", limits_.max_nodes, " nodes once its aliases are expanded"),
          std::to_string(limits_.max_nodes)};
    }
    const size_t reached = stack_.size() + depth;
    if (reached > limits_.max_depth) {
      throw LimitPassed{mark, absl::StrCat("nested deeper than ", limits_.max_depth, " levels"),
                        std::to_string(limits_.max_depth)};
    }
    if (!stack_.empty()) stack_.back().deepest = std::max(stack_.back().deepest, reached);
  }
  void open(const YAML::Mark& mark, YAML::anchor_t anchor) {
    add(mark, 1, 1);
    stack_.push_back(Open{anchor, nodes_ - 1, stack_.size() + 1});
  }
  void close() {
    if (stack_.empty()) return;
    const Open done = stack_.back();
    stack_.pop_back();
    if (!stack_.empty()) stack_.back().deepest = std::max(stack_.back().deepest, done.deepest);
    if (done.anchor != YAML::NullAnchor) {
      anchored_[done.anchor] = Size{nodes_ - done.nodes_before, done.deepest - stack_.size()};
    }
  }

  const YamlLimits& limits_;
  size_t nodes_ = 0;
  size_t aliases_ = 0;
  std::vector<Open> stack_;
  std::unordered_map<YAML::anchor_t, Size> anchored_;
};

int lineOf(const YAML::Mark& mark) { return mark.is_null() ? 1 : mark.line + 1; }

}  // namespace

absl::Status loadYaml(std::string_view text, const std::string& file, YAML::Node* out,
                      const YamlLimits& limits) {
  if (text.size() > limits.max_bytes) {
    return errors::withReason(absl::InvalidArgumentError(absl::StrCat(
                                  file, ": the text is ", text.size(), " bytes, more than the ",
                                  limits.max_bytes, " allowed")),
                              v1::FILE_TOO_LARGE,
                              {{"path", file}, {"limit", std::to_string(limits.max_bytes)}});
  }
  const std::string copy(text);
  try {
    std::istringstream in(copy);
    YAML::Parser parser(in);
    CountingHandler counter(limits);
    // The first document only, as YAML::Load reads.
    parser.HandleNextDocument(counter);
    *out = YAML::Load(copy);
  } catch (const LimitPassed& e) {
    absl::Status refused = absl::InvalidArgumentError(
        absl::StrCat(file, ":", lineOf(e.mark), ": refused: the YAML has ", e.what));
    // A cap passed; the caller says what else is wrong with the text.
    if (!e.limit.empty()) {
      refused = errors::withReason(std::move(refused), v1::LIMIT_EXCEEDED,
                                   {{"path", file}, {"limit", e.limit}});
    }
    return refused;
  } catch (const YAML::Exception& e) {
    return absl::InvalidArgumentError(
        absl::StrCat(file, ":", lineOf(e.mark), ": not valid YAML: ", e.msg));
  }
  return absl::OkStatus();
}

absl::Status guardYamlParse(const std::string& file, const std::function<absl::Status()>& parse) {
  try {
    return parse();
  } catch (const YAML::Exception& e) {
    return absl::InvalidArgumentError(absl::StrCat(file, ":", lineOf(e.mark), ": ", e.msg));
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat(file, ": ", e.what()));
  }
}

}  // namespace behaviorlib::server_kit
