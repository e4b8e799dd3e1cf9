// protoc-gen-behaviorlib: a protoc plugin that turns behavior declarations into
// the behaviors' public API (decision 21).
//
// For a file X.proto in which messages carry `option (behaviorlib.v1.declare)`,
// it writes:
//   - X_services.proto: for each declared `FooParameters`, the messages
//     `FooActivateRequest` and `FooModifyRequest` and the typed service `Foo`
//     with the seven lifecycle RPCs and the (behaviorlib.v1.behavior) option,
//     documented from the declaration;
//   - X.behaviors.h: for C++, `Foo behaviorServiceOf(const FooParameters*);`
//     declared in the package's namespace, so that a behavior system registers
//     a behavior by its class alone (BehaviorSystemBuilder::add<FooBehavior>()).
//
//   protoc --plugin=protoc-gen-behaviorlib=... --behaviorlib_out=GEN -I ROOT X.proto
//
// The generated .proto is compiled like any other, so gRPC, reflection and
// grpcurl see ordinary services.

#include <google/protobuf/compiler/code_generator.h>
#include <google/protobuf/compiler/plugin.h>
#include <google/protobuf/descriptor.h>
#include <google/protobuf/io/zero_copy_stream.h>

#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "behaviorlib/v1/options.pb.h"

namespace behaviorlib::codegen {
namespace {

using google::protobuf::Descriptor;
using google::protobuf::FileDescriptor;
using google::protobuf::SourceLocation;
using google::protobuf::compiler::GeneratorContext;

constexpr int kCommentWidth = 78;
constexpr std::string_view kSuffix = "Parameters";

std::string replaceAll(std::string text, const std::string& from, const std::string& to) {
  for (size_t at = text.find(from); at != std::string::npos; at = text.find(from, at + to.size())) {
    text.replace(at, from.size(), to);
  }
  return text;
}

// `text` as // comment lines indented by `indent`, words wrapped at
// kCommentWidth; blank lines in it are kept as paragraph breaks.
std::string comment(const std::string& text, const std::string& indent) {
  std::string out;
  std::istringstream lines(text);
  std::string line, current;
  auto flush = [&] {
    out += indent + "//" + (current.empty() ? "" : " " + current) + "\n";
    current.clear();
  };
  bool pending_words = false;
  while (std::getline(lines, line)) {
    std::istringstream words(line);
    std::string word;
    bool any = false;
    while (words >> word) {
      any = true;
      if (!current.empty() && indent.size() + 3 + current.size() + 1 + word.size() >
                                  static_cast<size_t>(kCommentWidth)) {
        flush();
      }
      current += (current.empty() ? "" : " ") + word;
      pending_words = true;
    }
    if (!any && pending_words) {  // a blank line: a paragraph break
      flush();
      out += indent + "//\n";
      pending_words = false;
    }
  }
  if (!current.empty()) flush();
  // A trailing paragraph break adds nothing.
  while (out.size() >= indent.size() + 3 && out.ends_with(indent + "//\n")) {
    out.resize(out.size() - indent.size() - 3);
  }
  return out;
}

std::string leadingComment(const Descriptor& message) {
  SourceLocation location;
  if (!message.GetSourceLocation(&location)) return {};
  return location.leading_comments;
}

struct Declared {
  const Descriptor* parameters;
  v1::BehaviorDeclaration declaration;
  std::string service;  // FooParameters -> Foo
};

bool collect(const FileDescriptor& file, std::vector<Declared>* out, std::string* error) {
  for (int i = 0; i < file.message_type_count(); ++i) {
    const Descriptor* message = file.message_type(i);
    if (!message->options().HasExtension(v1::declare)) continue;
    Declared d{message, message->options().GetExtension(v1::declare), {}};
    const std::string& name = message->name();
    if (!name.ends_with(kSuffix) || name.size() == kSuffix.size()) {
      *error = file.name() + ": " + name + " declares a behavior but its name does not end in '" +
               std::string(kSuffix) + "' (FooParameters declares the service Foo)";
      return false;
    }
    if (d.declaration.name().empty()) {
      *error = file.name() + ": " + name + " declares a behavior without a name";
      return false;
    }
    for (char c : d.declaration.name()) {
      if (!(c == '_' || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9'))) {
        *error = file.name() + ": " + name + " declares the behavior '" + d.declaration.name() +
                 "': a name is upper snake case (TAKE_OFF)";
        return false;
      }
    }
    if (d.declaration.kind() == v1::BEHAVIOR_KIND_UNSPECIFIED) {
      *error = file.name() + ": " + name + " declares " + d.declaration.name() +
               " without its kind (BEHAVIOR_KIND_GOAL_BASED or BEHAVIOR_KIND_RECURRENT)";
      return false;
    }
    d.service = name.substr(0, name.size() - kSuffix.size());
    out->push_back(std::move(d));
  }
  return true;
}

std::string kindName(v1::BehaviorKind kind) { return v1::BehaviorKind_Name(kind); }

// The documentation of one RPC: the declaration's text, else the generic one.
std::string rpcDoc(const std::string& given, const std::string& generic, const std::string& name) {
  return given.empty() ? replaceAll(generic, "{N}", name) : given;
}

std::string serviceProto(const FileDescriptor& file, const std::vector<Declared>& declared) {
  std::ostringstream p;
  p << "// Generated by protoc-gen-behaviorlib from " << file.name() << ". Do not edit:\n"
    << "// each behavior is declared once, by its parameters message there.\n"
    << "syntax = \"proto3\";\n\n";
  if (!file.package().empty()) p << "package " << file.package() << ";\n\n";
  p << "import \"behaviorlib/v1/behavior.proto\";\n"
    << "import \"behaviorlib/v1/options.proto\";\n"
    << "import \"" << file.name() << "\";\n\n"
    << "option cc_enable_arenas = true;\n";
  for (const Declared& d : declared) {
    const std::string& n = d.declaration.name();
    const std::string params = "." + d.parameters->full_name();
    p << "\n// " << std::string(75, '-') << "\n// " << n << "\n// " << std::string(75, '-')
      << "\n\n";
    p << comment("Request to activate " + n + ".", "") << "message " << d.service
      << "ActivateRequest {\n"
      << comment(
             "Optional idempotency key: a retry with the same id returns the same activation "
             "instead of starting a new one.",
             "  ")
      << "  string request_id = 1;\n"
      << comment("The parameters.", "  ") << "  " << params << " parameters = 2;\n}\n\n";
    p << comment("Request to modify an active " + n + ".", "") << "message " << d.service
      << "ModifyRequest {\n"
      << comment(
             "Optional: the activation to modify; a different current activation is refused with "
             "ABORTED.",
             "  ")
      << "  string activation_id = 1;\n"
      << comment(rpcDoc(d.declaration.modify_parameters_doc(),
                        "Parameters to change; fields left unset keep their current values.", n),
                 "  ")
      << "  " << params << " parameters = 2;\n}\n\n";
    const std::string description = leadingComment(*d.parameters);
    p << comment(description.empty() ? n + "." : description, "") << "service " << d.service
      << " {\n"
      << "  option (behaviorlib.v1.behavior) = {\n"
      << "    name: \"" << n << "\"\n"
      << "    kind: " << kindName(d.declaration.kind()) << "\n"
      << "    parameters_type: \"" << d.parameters->full_name() << "\"\n"
      << "  };\n";
    const auto& dd = d.declaration;
    struct Rpc {
      const char* name;
      std::string request, response, doc;
    };
    const std::vector<Rpc> rpcs = {
        {"Activate", d.service + "ActivateRequest", ".behaviorlib.v1.ActivateResponse",
         rpcDoc(dd.activate_doc(),
                "Activates {N}. INVALID_ARGUMENT for bad parameters (naming the parameter), "
                "FAILED_PRECONDITION when already active or when CheckSituation refuses.",
                n)},
        {"Deactivate", ".behaviorlib.v1.DeactivateRequest", ".behaviorlib.v1.DeactivateResponse",
         rpcDoc(dd.deactivate_doc(), "Ends the activation with cause INTERRUPTED.", n)},
        {"CheckActivation", ".behaviorlib.v1.CheckActivationRequest",
         ".behaviorlib.v1.CheckActivationResponse",
         rpcDoc(dd.check_activation_doc(),
                "Whether {N} is active, with which parameters, since when.", n)},
        {"CheckSituation", ".behaviorlib.v1.CheckSituationRequest",
         ".behaviorlib.v1.CheckSituationResponse",
         rpcDoc(dd.check_situation_doc(), "Whether {N} can be activated now, and why not.", n)},
        {"Pause", ".behaviorlib.v1.PauseRequest", ".behaviorlib.v1.PauseResponse",
         rpcDoc(dd.pause_doc(), "Pauses {N}.", n)},
        {"Resume", ".behaviorlib.v1.ResumeRequest", ".behaviorlib.v1.ResumeResponse",
         rpcDoc(dd.resume_doc(), "Resumes a paused {N}.", n)},
        {"Modify", d.service + "ModifyRequest", ".behaviorlib.v1.ModifyResponse",
         rpcDoc(dd.modify_doc(),
                "Changes the parameters of an active {N}; fields left unset keep their values.",
                n)},
    };
    for (const Rpc& rpc : rpcs) {
      p << comment(rpc.doc, "  ") << "  rpc " << rpc.name << "(" << rpc.request << ") returns ("
        << rpc.response << ");\n";
    }
    p << "}\n";
  }
  return p.str();
}

std::string cppNamespace(const std::string& package) { return replaceAll(package, ".", "::"); }

std::string behaviorsHeader(const FileDescriptor& file, const std::string& base,
                            const std::vector<Declared>& declared) {
  std::ostringstream h;
  h << "// Generated by protoc-gen-behaviorlib from " << file.name() << ". Do not edit.\n"
    << "// Maps each declared behavior's parameters message to its typed service, for\n"
    << "// BehaviorSystemBuilder::add<BehaviorClass>().\n"
    << "#pragma once\n\n"
    << "#include \"" << base << "_services.grpc.pb.h\"\n\n";
  const std::string ns = cppNamespace(file.package());
  if (!ns.empty()) h << "namespace " << ns << " {\n\n";
  for (const Declared& d : declared) {
    h << "/// " << d.declaration.name() << "\n"
      << d.service << " behaviorServiceOf(const " << d.parameters->name() << "*);\n";
  }
  if (!ns.empty()) h << "\n}  // namespace " << ns << "\n";
  return h.str();
}

void write(GeneratorContext* context, const std::string& name, const std::string& content) {
  std::unique_ptr<google::protobuf::io::ZeroCopyOutputStream> out(context->Open(name));
  void* data = nullptr;
  int size = 0;
  size_t written = 0;
  while (written < content.size() && out->Next(&data, &size)) {
    const size_t n = std::min(content.size() - written, static_cast<size_t>(size));
    std::copy_n(content.data() + written, n, static_cast<char*>(data));
    written += n;
    if (n < static_cast<size_t>(size)) out->BackUp(size - static_cast<int>(n));
  }
}

class Generator final : public google::protobuf::compiler::CodeGenerator {
 public:
  // Parameters use proto3 `optional` (presence), which the generator only
  // refers to by message.
  uint64_t GetSupportedFeatures() const override { return FEATURE_PROTO3_OPTIONAL; }

  bool Generate(const FileDescriptor* file, const std::string& /*parameter*/,
                GeneratorContext* context, std::string* error) const override {
    std::vector<Declared> declared;
    if (!collect(*file, &declared, error)) return false;
    if (declared.empty()) {
      *error = file->name() + " declares no behavior (no message with option " +
               "(behaviorlib.v1.declare))";
      return false;
    }
    std::string base = file->name();
    if (base.ends_with(".proto")) base.resize(base.size() - 6);
    write(context, base + "_services.proto", serviceProto(*file, declared));
    write(context, base + ".behaviors.h", behaviorsHeader(*file, base, declared));
    return true;
  }
};

}  // namespace
}  // namespace behaviorlib::codegen

int main(int argc, char* argv[]) {
  behaviorlib::codegen::Generator generator;
  return google::protobuf::compiler::PluginMain(argc, argv, &generator);
}
