"""The typed services of Python behaviors, built at run time: a port of protoc-gen-behaviorlib
(proto/codegen/protoc_gen_behaviorlib.cc), which the C++ build runs on every .proto that
declares behaviors.

For a file X.proto whose messages `FooParameters` carry `option (behaviorlib.v1.declare)`, the
C++ build compiles the generated X_services.proto: for each declared behavior the messages
`FooActivateRequest {request_id = 1; parameters = 2}` and `FooModifyRequest {activation_id = 1;
parameters = 2}`, and the service `Foo` with the (behaviorlib.v1.behavior) option and the seven
lifecycle methods. A Python process has no such generated module, so services_file() builds the
same FileDescriptorProto (same file name, package, imports, messages, field numbers, service,
option and methods) from the declaring file's descriptor, with the generator's comments as
source info, and add_services_file() puts it into the default descriptor pool: the typed
service is then served, described by reflection and called by grpcurl exactly as a C++
system's. The declaration rules are the generator's, with its messages: a declared message's
name ends in "Parameters", its behavior has an upper snake case name and a kind.

Comments come from the declaring file's documented form (a FileDescriptorProto with source
info, from a descriptor set such as the package's behaviorlib/v1/descriptors.binpb), else from
the comments parameters.leading_comment knows; a message without any gets the behavior's name
and a full stop, as the generator writes it for an undocumented message.
"""

from google.protobuf import descriptor_pb2, descriptor_pool

from behaviorlib.v1 import options_pb2

from . import _protocol, parameters

SUFFIX = "Parameters"
_COMMENT_WIDTH = 78
_RULE = "// " + "-" * 75

# The seven lifecycle methods: name, request (None: the behavior's own), response, the
# declaration's documentation field, the generic documentation ({N}: the behavior's name).
_METHODS = (
    ("Activate", None, "ActivateResponse", "activate_doc",
     "Activates {N}. INVALID_ARGUMENT for bad parameters (naming the parameter), "
     "FAILED_PRECONDITION when already active or when CheckSituation refuses."),
    ("Deactivate", "DeactivateRequest", "DeactivateResponse", "deactivate_doc",
     "Ends the activation with cause INTERRUPTED."),
    ("CheckActivation", "CheckActivationRequest", "CheckActivationResponse",
     "check_activation_doc", "Whether {N} is active, with which parameters, since when."),
    ("CheckSituation", "CheckSituationRequest", "CheckSituationResponse", "check_situation_doc",
     "Whether {N} can be activated now, and why not."),
    ("Pause", "PauseRequest", "PauseResponse", "pause_doc", "Pauses {N}."),
    ("Resume", "ResumeRequest", "ResumeResponse", "resume_doc", "Resumes a paused {N}."),
    ("Modify", None, "ModifyResponse", "modify_doc",
     "Changes the parameters of an active {N}; fields left unset keep their values."),
)


def find_service(full_name):
    """A service of the default pool by full name (a typed service once its file is added)."""
    return descriptor_pool.Default().FindServiceByName(full_name)


def services_file_name(file_name):
    """The generated file's name: X.proto -> X_services.proto."""
    base = file_name[:-len(".proto")] if file_name.endswith(".proto") else file_name
    return base + "_services.proto"


def service_name(message_descriptor):
    """The typed service's full name for a declared parameters message (FooParameters -> Foo in
    its package)."""
    return message_descriptor.full_name[:-len(SUFFIX)]


def _comment(text, indent):
    """`text` as // comment lines indented by `indent`, words wrapped at 78 columns, blank
    lines kept as paragraph breaks (the generator's comment())."""
    out = []
    current = ""
    pending_words = False
    for line in text.split("\n"):
        words = line.split()
        for word in words:
            if current and len(indent) + 3 + len(current) + 1 + len(word) > _COMMENT_WIDTH:
                out.append(f"{indent}// {current}")
                current = ""
            current += (" " if current else "") + word
            pending_words = True
        if not words and pending_words:
            out.append(f"{indent}// {current}" if current else f"{indent}//")
            current = ""
            out.append(f"{indent}//")
            pending_words = False
    if current:
        out.append(f"{indent}// {current}")
    while out and out[-1] == f"{indent}//":
        out.pop()
    return out


class _Text:
    """The generated .proto's lines, and the source info of its elements (their comments and
    where they are), as protoc would record them compiling that text."""

    def __init__(self):
        self.lines = []
        self.info = descriptor_pb2.SourceCodeInfo()

    def add(self, *lines):
        self.lines.extend(lines)

    def element(self, path, comment_lines, indent, *lines):
        """Adds an element of one or more lines after its comment, recording its location."""
        self.lines.extend(comment_lines)
        first = len(self.lines)
        self.lines.extend(lines)
        location = self.info.location.add(path=path)
        last = len(self.lines) - 1
        if first == last:
            location.span.extend([first, len(indent), len(self.lines[last])])
        else:
            location.span.extend([first, len(indent), last, len(self.lines[last])])
        if comment_lines:
            location.leading_comments = "".join(
                line[len(indent) + 2:] + "\n" for line in comment_lines)
        return location

    def extend_span(self, location):
        """Makes `location`, opened by element(), end at the last line added."""
        first, column = location.span[0], location.span[1]
        last = len(self.lines) - 1
        del location.span[:]
        location.span.extend([first, column, last, len(self.lines[last])])


def _declarations(file_descriptor):
    """The declared behaviors of a file, in order: (parameters descriptor, declaration).
    Raises ValueError on a declaration the generator refuses."""
    out = []
    proto = descriptor_pb2.FileDescriptorProto()
    file_descriptor.CopyToProto(proto)  # the messages in declaration order
    for message in (file_descriptor.message_types_by_name[m.name] for m in proto.message_type):
        message_options = message.GetOptions()
        if not message_options.HasExtension(options_pb2.declare):
            continue
        declaration = message_options.Extensions[options_pb2.declare]
        where = f"{file_descriptor.name}: {message.name}"
        if not message.name.endswith(SUFFIX) or message.name == SUFFIX:
            raise ValueError(f"{where} declares a behavior but its name does not end in "
                             f"'{SUFFIX}' (FooParameters declares the service Foo)")
        if not declaration.name:
            raise ValueError(f"{where} declares a behavior without a name")
        if any(not (c == "_" or "A" <= c <= "Z" or "0" <= c <= "9") for c in declaration.name):
            raise ValueError(f"{where} declares the behavior '{declaration.name}': a name is "
                             "upper snake case (TAKE_OFF)")
        if declaration.kind == options_pb2.BEHAVIOR_KIND_UNSPECIFIED:
            raise ValueError(f"{where} declares {declaration.name} without its kind "
                             "(BEHAVIOR_KIND_GOAL_BASED or BEHAVIOR_KIND_RECURRENT)")
        out.append((message, declaration))
    return out


def _leading_comment(documented, message):
    """The leading comment of top-level `message`: as written in `documented` (a
    FileDescriptorProto with source info, or None), else in one paragraph from the comments
    known to parameters.leading_comment (a message declared in Python, a descriptor set)."""
    if documented is not None:
        index = next((i for i, m in enumerate(documented.message_type)
                      if m.name == message.name), None)
        for location in documented.source_code_info.location:
            if index is not None and list(location.path) == [4, index]:
                return location.leading_comments
    return parameters.leading_comment(message.full_name)


def services_file(file_descriptor, documented=None):
    """The FileDescriptorProto, with source info, of the services the generator makes for the
    behaviors that `file_descriptor` (a FileDescriptor) declares; `documented` is that file's
    FileDescriptorProto with source info, for the behaviors' descriptions."""
    declared = _declarations(file_descriptor)
    if not declared:
        raise ValueError(f"{file_descriptor.name} declares no behavior (no message with option "
                         "(behaviorlib.v1.declare))")
    package = file_descriptor.package
    scope = f".{package}." if package else "."
    out = descriptor_pb2.FileDescriptorProto(
        name=services_file_name(file_descriptor.name), package=package, syntax="proto3",
        dependency=["behaviorlib/v1/behavior.proto", "behaviorlib/v1/options.proto",
                    file_descriptor.name])
    out.options.cc_enable_arenas = True
    text = _Text()
    text.add(f"// Generated by protoc-gen-behaviorlib from {file_descriptor.name}. Do not edit:",
             "// each behavior is declared once, by its parameters message there.",
             'syntax = "proto3";', "")
    if package:
        text.add(f"package {package};", "")
    text.add('import "behaviorlib/v1/behavior.proto";', 'import "behaviorlib/v1/options.proto";',
             f'import "{file_descriptor.name}";', "", "option cc_enable_arenas = true;")
    for message_type, declaration in declared:
        name = declaration.name
        short = message_type.name[:-len(SUFFIX)]
        parameters_type = "." + message_type.full_name
        text.add("", _RULE, f"// {name}", _RULE, "")
        for request, comment, first_field, first_comment, parameters_comment in (
                ("ActivateRequest", f"Request to activate {name}.", "request_id",
                 "Optional idempotency key: a retry with the same id returns the same activation "
                 "instead of starting a new one.", "The parameters."),
                ("ModifyRequest", f"Request to modify an active {name}.", "activation_id",
                 "Optional: the activation to modify; a different current activation is refused "
                 "with ABORTED.",
                 declaration.modify_parameters_doc
                 or "Parameters to change; fields left unset keep their current values.")):
            index = len(out.message_type)
            message = out.message_type.add(name=short + request)
            _protocol.add_field(message, first_field, 1, "string")
            _protocol.add_field(message, "parameters", 2, "message", parameters_type)
            opened = text.element([4, index], _comment(comment, ""), "",
                                  f"message {short}{request} {{")
            text.element([4, index, 2, 0], _comment(first_comment, "  "), "  ",
                         f"  string {first_field} = 1;")
            text.element([4, index, 2, 1], _comment(parameters_comment, "  "), "  ",
                         f"  {parameters_type} parameters = 2;")
            text.add("}")
            text.extend_span(opened)
            text.add("")
        service_index = len(out.service)
        service = out.service.add(name=short)
        info = service.options.Extensions[options_pb2.behavior]
        info.name = name
        info.kind = declaration.kind
        info.parameters_type = message_type.full_name
        description = _leading_comment(documented, message_type)
        opened = text.element(
            [6, service_index], _comment(description or f"{name}.", ""), "",
            f"service {short} {{", "  option (behaviorlib.v1.behavior) = {", f'    name: "{name}"',
            f"    kind: {options_pb2.BehaviorKind.Name(declaration.kind)}",
            f'    parameters_type: "{message_type.full_name}"', "  };")
        for i, (method, request, response, doc_field, generic) in enumerate(_METHODS):
            request_type = (f"{short}{method}Request" if request is None
                            else f".behaviorlib.v1.{request}")
            service.method.add(name=method,
                               input_type=(scope + request_type if request is None
                                           else request_type),
                               output_type=f".behaviorlib.v1.{response}")
            doc = getattr(declaration, doc_field) or generic.replace("{N}", name)
            text.element([6, service_index, 2, i], _comment(doc, "  "), "  ",
                         f"  rpc {method}({request_type}) returns "
                         f"(.behaviorlib.v1.{response});")
        text.add("}")
        text.extend_span(opened)
    out.source_code_info.CopyFrom(text.info)
    return out


def add_services_file(file_descriptor, documented=None):
    """Builds the services file of `file_descriptor`, adds it to the default pool (once per
    process) and its comments to parameters.leading_comment's (ListBehaviors describes a
    behavior by its service's comment). Returns (the pool's FileDescriptor, the
    FileDescriptorProto with source info)."""
    proto = services_file(file_descriptor, documented)
    parameters.load_descriptor_set(
        descriptor_pb2.FileDescriptorSet(file=[proto]).SerializeToString())
    return _protocol.add_file(proto), proto
