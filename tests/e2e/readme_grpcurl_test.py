"""The README's grpcurl session, run as written against the local stack.

    /usr/bin/python3 tests/e2e/readme_grpcurl_test.py --build-dir build

Reads the two fenced blocks of the README's "Manual control with grpcurl"
section (each announced by a `<!-- readme_grpcurl_test: ... -->` comment):
the set-up block, whose launcher line starts the stack (here with a temporary
run directory and --time-scale 2) and whose COORDINATOR=/BASIC= lines are run
by bash to find the addresses; and the session block, whose grpcurl commands
are run one by one, in order, by bash, with `grpcurl` on the PATH being this
file's grpcurl-compatible runner. Each command must exit as grpcurl would
(0, or 68 = 64 + DEADLINE_EXCEEDED for a stream ended by -max-time) and print
what the README says it prints; at the end the simulator must show that the
vehicle flew and landed. The stack is stopped even when a step fails.

grpcurl is not packaged for Debian 12, so the runner is this file itself:

    readme_grpcurl_test.py --grpcurl [flags] ADDRESS list [SERVICE]
    readme_grpcurl_test.py --grpcurl [flags] ADDRESS describe SYMBOL
    readme_grpcurl_test.py --grpcurl [flags] ADDRESS SERVICE/METHOD

It learns everything through server reflection (tests/integration/
reflection_client.py, on python3-grpcio and python3-protobuf only), parses
flags as grpcurl does (Go's flag package: flags first, -name value or
-name=value) and supports -plaintext (required: it has no TLS), -d JSON,
-max-time seconds, -connect-timeout, -emit-defaults, -keep-proto-names and
-allow-unknown-fields; unary and server-streaming calls. Replies are printed
as grpcurl prints them (protobuf JSON, lowerCamelCase names, two-space
indent); a failed call prints "ERROR:\\n  Code: ...\\n  Message: ..." on stderr
and exits with 64 + the status code.
"""

import argparse
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import unittest

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
README = os.path.join(REPO, "README.md")
LAUNCHER = os.path.join(REPO, "deploy", "local", "launch.py")
BUILD_DIR = os.environ.get("BEHAVIORLIB_BUILD_DIR", os.path.join(REPO, "build"))
# As local_demo_test.py: at 2x the stack leaves room for the other test ctest
# may run next to this one.
TIME_SCALE = "2"
MARKER = "<!-- readme_grpcurl_test: {} -->"

sys.path.insert(0, os.path.join(REPO, "deploy", "local"))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import grpc  # noqa: E402
from google.protobuf import descriptor_pb2, json_format  # noqa: E402

import demo  # noqa: E402  (deploy/local: the launcher's own reflection clients)
import reflection_client as rc  # noqa: E402
import rpc  # noqa: E402
from local_demo_test import kill_launched  # noqa: E402

# --- the grpcurl-compatible runner -------------------------------------------

# grpcurl exits with 64 + the status code when a call fails, 1 when it cannot
# do what was asked (dial, resolve, parse), 2 on a usage error.
STATUS_CODE_OFFSET = 64
_BOOL_FLAGS = ("plaintext", "emit-defaults", "keep-proto-names", "allow-unknown-fields")
_VALUE_FLAGS = ("d", "max-time", "connect-timeout")


class Failure(Exception):
    """What grpcurl's fail() does: a message, then exit 1 (2 for usage)."""

    def __init__(self, message, exit_code=1):
        super().__init__(message)
        self.exit_code = exit_code


def _go_code_name(code):
    """grpc.StatusCode.DEADLINE_EXCEEDED -> "DeadlineExceeded" (Go's names)."""
    if code in (grpc.StatusCode.OK, grpc.StatusCode.CANCELLED):
        return {"OK": "OK", "CANCELLED": "Canceled"}[code.name]
    return "".join(part.capitalize() for part in code.name.split("_"))


def parse_flags(argv):
    """Go flag package semantics: flags until the first non-flag argument or
    "--"; "-name value", "-name=value", "--name" alike. Returns (flags,
    positional arguments)."""
    flags = {"plaintext": False, "d": "", "max-time": 0.0, "connect-timeout": 0.0,
             "emit-defaults": False, "keep-proto-names": False, "allow-unknown-fields": False}
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg == "--":
            i += 1
            break
        if len(arg) < 2 or arg[0] != "-":
            break
        name = arg[2:] if arg.startswith("--") else arg[1:]
        name, has_value, value = name.partition("=")
        i += 1
        if name in _BOOL_FLAGS:
            if has_value and value not in ("true", "false", "1", "0", "t", "f", "TRUE", "FALSE",
                                           "True", "False", "T", "F"):
                raise Failure(f'invalid boolean value "{value}" for -{name}', 2)
            flags[name] = not has_value or value in ("true", "1", "t", "TRUE", "True", "T")
        elif name in _VALUE_FLAGS:
            if not has_value:
                if i >= len(argv):
                    raise Failure(f"flag needs an argument: -{name}", 2)
                value = argv[i]
                i += 1
            if name == "d":
                flags[name] = value
            else:
                try:
                    flags[name] = float(value)
                except ValueError:
                    raise Failure(f'invalid value "{value}" for flag -{name}: parse error', 2)
                if flags[name] < 0:
                    raise Failure(f"The -{name} argument must not be negative.", 2)
        else:
            raise Failure(f"flag provided but not defined: -{name}", 2)
    return flags, argv[i:]


_SCALAR_TYPES = {
    getattr(descriptor_pb2.FieldDescriptorProto, "TYPE_" + name.upper()): name
    for name in ("double", "float", "int64", "uint64", "int32", "fixed64", "fixed32", "bool",
                 "string", "bytes", "uint32", "sfixed32", "sfixed64", "sint32", "sint64")
}


class _Describer:
    """Proto-like text of one element of a file, with its comments, as
    grpcurl's describe prints it (options left out)."""

    def __init__(self, file):
        self.file = file
        self.proto3 = file.syntax == "proto3"
        self.comments = {tuple(loc.path): loc.leading_comments
                         for loc in file.source_code_info.location if loc.leading_comments}
        self.elements = {}  # full name -> (kind, path, proto, parent message proto or None)
        prefix = f"{file.package}." if file.package else ""
        for i, m in enumerate(file.message_type):
            self._message(m, prefix, (4, i))
        for i, e in enumerate(file.enum_type):
            self._enum(e, prefix, (5, i))
        for i, s in enumerate(file.service):
            self.elements[prefix + s.name] = ("a service", (6, i), s, None)
            for j, method in enumerate(s.method):
                self.elements[f"{prefix}{s.name}.{method.name}"] = (
                    "a method", (6, i, 2, j), method, None)

    def _message(self, m, scope, path):
        name = scope + m.name
        self.elements[name] = ("a message", path, m, None)
        for i, field in enumerate(m.field):
            self.elements[f"{name}.{field.name}"] = ("a field", path + (2, i), field, m)
        for i, nested in enumerate(m.nested_type):
            self._message(nested, name + ".", path + (3, i))
        for i, nested in enumerate(m.enum_type):
            self._enum(nested, name + ".", path + (4, i))

    def _enum(self, e, scope, path):
        self.elements[scope + e.name] = ("an enum", path, e, None)
        for i, value in enumerate(e.value):
            self.elements[scope + value.name] = ("an enum value", path + (2, i), value, None)

    def _comment(self, path, indent):
        text = self.comments.get(tuple(path), "")
        return [f"{indent}//{line}" for line in text.rstrip("\n").split("\n")] if text else []

    def _field_type(self, field, message):
        if field.type in (field.TYPE_MESSAGE, field.TYPE_ENUM, field.TYPE_GROUP):
            if message is not None and field.label == field.LABEL_REPEATED:
                entry = next((n for n in message.nested_type
                              if n.options.map_entry and field.type_name.endswith("." + n.name)),
                             None)
                if entry is not None:
                    key = self._field_type(entry.field[0], None)
                    value = self._field_type(entry.field[1], None)
                    return f"map<{key}, {value}>"
            return field.type_name
        return _SCALAR_TYPES[field.type]

    def _field(self, field, message, path, indent):
        kind = self._field_type(field, message)
        label = ""
        if not kind.startswith("map<"):
            if field.label == field.LABEL_REPEATED:
                label = "repeated "
            elif field.label == field.LABEL_REQUIRED:
                label = "required "
            elif field.proto3_optional or not self.proto3:
                label = "optional "
        return self._comment(path, indent) + [
            f"{indent}{label}{kind} {field.name} = {field.number};"]

    def _method(self, method, path, indent):
        request = ("stream " if method.client_streaming else "") + method.input_type
        response = ("stream " if method.server_streaming else "") + method.output_type
        return self._comment(path, indent) + [
            f"{indent}rpc {method.name} ( {request} ) returns ( {response} );"]

    def _message_text(self, m, path, indent):
        lines = self._comment(path, indent) + [f"{indent}message {m.name} {{"]
        inner = indent + "  "
        maps = {n.name for n in m.nested_type if n.options.map_entry}
        done_oneofs = set()
        for i, field in enumerate(m.field):
            real_oneof = field.HasField("oneof_index") and not field.proto3_optional
            if not real_oneof:
                lines += self._field(field, m, path + (2, i), inner)
                continue
            if field.oneof_index in done_oneofs:
                continue
            done_oneofs.add(field.oneof_index)
            oneof_path = path + (8, field.oneof_index)
            lines += self._comment(oneof_path, inner)
            lines.append(f"{inner}oneof {m.oneof_decl[field.oneof_index].name} {{")
            for j, member in enumerate(m.field):
                if member.HasField("oneof_index") and member.oneof_index == field.oneof_index:
                    lines += self._field(member, m, path + (2, j), inner + "  ")
            lines.append(f"{inner}}}")
        for i, nested in enumerate(m.nested_type):
            if nested.name not in maps:
                lines += self._message_text(nested, path + (3, i), inner)
        for i, nested in enumerate(m.enum_type):
            lines += self._enum_text(nested, path + (4, i), inner)
        return lines + [f"{indent}}}"]

    def _enum_text(self, e, path, indent):
        lines = self._comment(path, indent) + [f"{indent}enum {e.name} {{"]
        for i, value in enumerate(e.value):
            lines += self._comment(path + (2, i), indent + "  ")
            lines.append(f"{indent}  {value.name} = {value.number};")
        return lines + [f"{indent}}}"]

    def describe(self, full_name):
        """(kind, text) of element `full_name`, or None when not in the file."""
        if full_name not in self.elements:
            return None
        kind, path, proto, parent = self.elements[full_name]
        if kind == "a service":
            lines = self._comment(path, "") + [f"service {proto.name} {{"]
            for j, method in enumerate(proto.method):
                lines += self._method(method, path + (2, j), "  ")
            lines.append("}")
        elif kind == "a method":
            lines = self._method(proto, path, "")
        elif kind == "a message":
            lines = self._message_text(proto, path, "")
        elif kind == "a field":
            lines = self._field(proto, parent, path, "")
        elif kind == "an enum":
            lines = self._enum_text(proto, path, "")
        else:
            lines = self._comment(path, "") + [f"{proto.name} = {proto.number};"]
        return kind, "\n".join(lines)


class _Deadline:
    """-max-time: one deadline for reflection and the call together."""

    def __init__(self, max_time_s):
        self.at = time.monotonic() + max_time_s if max_time_s > 0 else None

    def left(self, cap=None):
        if self.at is None:
            return cap
        left = max(self.at - time.monotonic(), 0.001)
        return min(left, cap) if cap else left


def _reflect(call, what):
    try:
        return call()
    except rc.ReflectionError as error:
        raise Failure(f"{what}: rpc error: code = {_go_code_name(error.code)} "
                      f"desc = {error.message}")
    except grpc.RpcError as error:
        raise Failure(f"{what}: rpc error: code = {_go_code_name(error.code())} "
                      f"desc = {error.details()}")


def _print_status(error, err):
    err.write(f"ERROR:\n  Code: {_go_code_name(error.code())}\n  Message: {error.details()}\n")
    err.flush()
    return STATUS_CODE_OFFSET + error.code().value[0]


def _request_messages(data):
    """The JSON objects of -d (grpcurl accepts several, concatenated)."""
    decoder = json.JSONDecoder()
    messages, pos = [], 0
    while True:
        while pos < len(data) and data[pos].isspace():
            pos += 1
        if pos == len(data):
            return messages
        value, pos = decoder.raw_decode(data, pos)
        messages.append(value)


def _invoke(address, flags, symbol, deadline, out, err):
    if "/" in symbol:
        service, _, method_name = symbol.rpartition("/")
    else:
        service, _, method_name = symbol.rpartition(".")
    if not service or not method_name:
        raise Failure(f'Error invoking method "{symbol}": given method name "{symbol}" is not '
                      "in expected format: 'service/method' or 'service.method'")
    try:
        files = rc.file_containing_symbol(address, service, timeout=deadline.left(10.0))
    except rc.ReflectionError as error:
        if error.code == grpc.StatusCode.NOT_FOUND:
            raise Failure(f'Error invoking method "{symbol}": target server does not expose '
                          f'service "{service}"')
        raise Failure(f'Error invoking method "{symbol}": {error}')
    pool = rc.pool_from_files(files)
    service_desc = pool.FindServiceByName(service)
    if method_name not in service_desc.methods_by_name:
        raise Failure(f'Error invoking method "{symbol}": service "{service}" does not include '
                      f'a method named "{method_name}"')
    method = service_desc.methods_by_name[method_name]
    if method.client_streaming:
        raise Failure(f'Error invoking method "{symbol}": this runner makes unary and '
                      "server-streaming calls only")
    request_class = rc.message_class(pool, method.input_type.full_name)
    response_class = rc.message_class(pool, method.output_type.full_name)
    try:
        values = _request_messages(flags["d"])
    except ValueError as error:
        raise Failure(f'Error invoking method "{symbol}": error getting request data: {error}')
    if len(values) > 1:
        raise Failure(f'Error invoking method "{symbol}": method "{service}.{method_name}" is '
                      f"not a client-streaming RPC, but request data contained {len(values)} "
                      "messages")
    request = request_class()
    if values:
        try:
            json_format.ParseDict(values[0], request,
                                  ignore_unknown_fields=flags["allow-unknown-fields"],
                                  descriptor_pool=pool)
        except json_format.ParseError as error:
            raise Failure(f'Error invoking method "{symbol}": error getting request data: {error}')

    def show(message):
        try:
            text = json_format.MessageToJson(
                message, indent=2, preserving_proto_field_name=flags["keep-proto-names"],
                including_default_value_fields=flags["emit-defaults"], descriptor_pool=pool)
        except TypeError:  # protobuf >= 26 renamed including_default_value_fields
            text = json_format.MessageToJson(
                message, indent=2, preserving_proto_field_name=flags["keep-proto-names"],
                always_print_fields_with_no_presence=flags["emit-defaults"],
                descriptor_pool=pool)
        out.write(text + "\n")
        out.flush()

    with grpc.insecure_channel(address) as channel:
        path = f"/{service}/{method_name}"
        try:
            if method.server_streaming:
                call = channel.unary_stream(path,
                                            request_serializer=request_class.SerializeToString,
                                            response_deserializer=response_class.FromString)
                for reply in call(request, timeout=deadline.left()):
                    show(reply)
            else:
                call = channel.unary_unary(path,
                                           request_serializer=request_class.SerializeToString,
                                           response_deserializer=response_class.FromString)
                show(call(request, timeout=deadline.left()))
        except grpc.RpcError as error:
            return _print_status(error, err)
    return 0


def grpcurl_main(argv, out=sys.stdout, err=sys.stderr):
    """Runs one grpcurl command line (without the program name); returns
    its exit code."""
    try:
        flags, args = parse_flags(argv)
        if not args:
            raise Failure("Too few arguments.", 2)
        if args[0] in ("list", "describe"):
            raise Failure("This runner needs a server address (it uses server reflection).", 2)
        address, args = args[0], args[1:]
        if not args:
            raise Failure("Too few arguments.", 2)
        verb = args[0] if args[0] in ("list", "describe") else "invoke"
        if verb != "invoke":
            args = args[1:]
        if verb == "invoke" and not args:
            raise Failure("Too few arguments.", 2)
        if len(args) > 1:
            raise Failure("Too many arguments.", 2)
        symbol = args[0] if args else ""
        if verb != "invoke" and flags["d"]:
            err.write("Warning: The -d argument is not used with 'list' or 'describe' verb.\n")
        if not flags["plaintext"]:
            # Real grpcurl would attempt TLS, which these servers do not speak.
            raise Failure(f'Failed to dial target host "{address}": this runner has no TLS; '
                          "the servers are plaintext: add -plaintext")
        deadline = _Deadline(flags["max-time"])
        with grpc.insecure_channel(address) as channel:
            try:
                grpc.channel_ready_future(channel).result(
                    timeout=deadline.left(flags["connect-timeout"] or 10.0))
            except grpc.FutureTimeoutError:
                raise Failure(f'Failed to dial target host "{address}": context deadline '
                              "exceeded")
        if verb == "list":
            if not symbol:
                services = _reflect(lambda: rc.list_services(address, timeout=deadline.left(10.0)),
                                    "Failed to list services")
                out.write("".join(f"{s}\n" for s in sorted(services)) or "(No services)\n")
            else:
                files = _reflect(lambda: rc.file_containing_symbol(
                    address, symbol, timeout=deadline.left(10.0)),
                    f'Failed to list methods for service "{symbol}"')
                try:
                    service = rc.pool_from_files(files).FindServiceByName(symbol)
                except KeyError:
                    raise Failure(f'Failed to list methods for service "{symbol}": Symbol '
                                  f'"{symbol}" is not a service')
                out.write("".join(f"{symbol}.{m.name}\n" for m in sorted(
                    service.methods, key=lambda m: m.name)) or "(No methods)\n")
            return 0
        if verb == "describe":
            if not symbol:
                raise Failure("This runner describes one symbol at a time.", 2)
            symbol = symbol.lstrip(".")
            files = _reflect(lambda: rc.file_containing_symbol(
                address, symbol, timeout=deadline.left(10.0)),
                f'Failed to resolve symbol "{symbol}"')
            described = _Describer(files[0]).describe(symbol)
            if described is None:
                raise Failure(f'Failed to resolve symbol "{symbol}": not found in {files[0].name}')
            kind, text = described
            out.write(f"{symbol} is {kind}:\n{text}\n")
            return 0
        return _invoke(address, flags, symbol, deadline, out, err)
    except Failure as failure:
        err.write(f"{failure}\n")
        if failure.exit_code == 2:
            err.write("Try 'grpcurl -help' for more details.\n")
        return failure.exit_code


# --- the README ------------------------------------------------------------------

def readme_block(text, name):
    """The lines of the fenced block right after MARKER.format(name)."""
    marker = MARKER.format(name)
    if text.count(marker) != 1:
        raise AssertionError(f"README.md must hold exactly one {marker}")
    after = text.split(marker, 1)[1].lstrip("\n")
    match = re.match(r"```[a-z]*\n(.*?)\n```", after, re.S)
    if not match:
        raise AssertionError(f"no fenced block right after {marker}")
    return match.group(1).split("\n")


def shell_commands(lines):
    """Groups the block's lines into commands as a shell reads them: a
    command continues over a trailing backslash or an open quote; blank and
    comment lines stand alone and are dropped."""
    commands, pending = [], ""
    for line in lines:
        if not pending and (not line.strip() or line.lstrip().startswith("#")):
            continue
        pending = f"{pending}\n{line}" if pending else line
        try:
            shlex.split(pending, comments=True)
        except ValueError:  # an open quote, or a trailing backslash
            continue
        commands.append(pending)
        pending = ""
    if pending:
        raise AssertionError(f"unterminated command in the README: {pending!r}")
    return commands


# --- what each documented command must show ----------------------------------------

def json_objects(text):
    """Every JSON object grpcurl printed, in order."""
    return _request_messages(text)


def _events(replies):
    """The BehaviorEvents of a (system or coordinator) WatchEvents output."""
    events = []
    for reply in replies:
        event = reply.get("event")
        if event is None:
            continue
        events.append(event.get("behaviorEvent", event))
    return events


def _finished(events, activation_id):
    return [e["finished"] for e in events
            if e.get("activationId") == activation_id and "finished" in e]


class Step:
    """One README command: a regular expression it must match (so the test
    and the README cannot drift apart unseen), the exit code, a check of its
    output, and optionally a condition to re-run it for (a state that takes
    a moment to hold, as a person would run it again)."""

    def __init__(self, pattern, check, exit_code=0, until=None):
        self.pattern = pattern
        self.check = check
        self.exit_code = exit_code
        self.until = until


def _check_coordinator_list(t, out, err, ids):
    services = out.split()
    for name in ("behaviorlib.v1.Coordinator", "grpc.health.v1.Health"):
        t.assertIn(name, services)


def _check_system_list(t, out, err, ids):
    services = out.split()
    for name in ("behaviorlib.v1.BehaviorSystem", "behaviorlib.v1.TakeOff",
                 "behaviorlib.v1.SelfLocalizeWithGroundTruth", "grpc.health.v1.Health"):
        t.assertIn(name, services)


def _check_describe_service(t, out, err, ids):
    t.assertTrue(out.startswith("behaviorlib.v1.TakeOff is a service:\n"), out)
    t.assertIn("// TAKE_OFF: takes off from the ground", out)
    t.assertIn("rpc Activate ( .behaviorlib.v1.TakeOffActivateRequest ) returns "
               "( .behaviorlib.v1.ActivateResponse );", out)
    t.assertIn("rpc CheckSituation ( .behaviorlib.v1.CheckSituationRequest ) returns "
               "( .behaviorlib.v1.CheckSituationResponse );", out)


def _check_describe_message(t, out, err, ids):
    t.assertTrue(out.startswith("behaviorlib.v1.TakeOffParameters is a message:\n"), out)
    t.assertIn("// Altitude to climb to, in metres", out)
    t.assertIn("optional double altitude_m = 1;", out)


def _check_system_behaviors(t, out, err, ids):
    (reply,) = json_objects(out)
    t.assertEqual(reply["system"], "basic_quadrotor_behaviors")
    t.assertEqual(reply["robotId"], "drone1")
    names = {b["name"] for b in reply["behaviors"]}
    t.assertLessEqual({"TAKE_OFF", "LAND", "SELF_LOCALIZE_WITH_GROUND_TRUTH"}, names)


def _check_fleet_behaviors(t, out, err, ids):
    (reply,) = json_objects(out)
    hosts = {b["description"]["name"]: (b["system"], b["systemState"])
             for b in reply["behaviors"]}
    t.assertEqual(hosts["TAKE_OFF"], ("basic_quadrotor_behaviors", "SYSTEM_STATE_UP"))
    t.assertEqual(hosts["FOLLOW_PATH"], ("quadrotor_motion_with_pid_control", "SYSTEM_STATE_UP"))


def _check_not_feasible(t, out, err, ids):
    (reply,) = json_objects(out)
    t.assertEqual(reply["system"], "basic_quadrotor_behaviors")
    t.assertFalse(reply["situation"].get("feasible", False), reply)
    t.assertTrue(any("pose" in r for r in reply["situation"].get("reasons", [])), reply)


def _check_localization_activated(t, out, err, ids):
    (reply,) = json_objects(out)
    t.assertTrue(reply.get("activationId"), reply)
    ids["localization"] = reply["activationId"]


def _feasible(out):
    replies = json_objects(out)
    return len(replies) == 1 and replies[0].get("feasible") is True


def _check_feasible(t, out, err, ids):
    t.assertTrue(_feasible(out), out)


def _check_typed_take_off(t, out, err, ids):
    (reply,) = json_objects(out)
    t.assertTrue(reply.get("activationId"), reply)
    t.assertEqual(reply["parameters"]["altitude_m"], 1.5)
    ids["typed_take_off"] = reply["activationId"]


def _check_deadline(t, err):
    t.assertIn("Code: DeadlineExceeded", err)


def _check_system_events(t, out, err, ids):
    _check_deadline(t, err)
    replies = json_objects(out)
    t.assertIn("start", replies[0])
    events = _events(replies)
    t.assertTrue(events, out)
    t.assertEqual({e["behavior"] for e in events}, {"TAKE_OFF"})
    mine = [e for e in events if e["activationId"] == ids["typed_take_off"]]
    t.assertIn("activated", mine[0], mine)
    t.assertEqual([f["cause"] for f in _finished(events, ids["typed_take_off"])],
                  ["TERMINATION_CAUSE_GOAL_ACHIEVED"], out)


def _check_deactivated(t, out, err, ids):
    (reply,) = json_objects(out)
    t.assertEqual(reply["system"], "basic_quadrotor_behaviors")
    t.assertEqual(reply["result"]["activationId"], ids["localization"])
    t.assertEqual(reply["result"]["cause"], "TERMINATION_CAUSE_INTERRUPTED")


def _check_mission_started(t, out, err, ids):
    (reply,) = json_objects(out)
    status = reply["status"]
    t.assertTrue(status["missionId"], reply)
    t.assertEqual(status["robotId"], "drone1")
    t.assertIn(status["state"], ("MISSION_STATE_PENDING", "MISSION_STATE_RUNNING"), reply)
    ids["mission"] = status["missionId"]


def _check_mission_watched(t, out, err, ids):
    statuses = [r["status"] for r in json_objects(out)]
    t.assertTrue(statuses, out)
    t.assertEqual({s["missionId"] for s in statuses}, {ids["mission"]})
    final = statuses[-1]
    t.assertEqual(final["state"], "MISSION_STATE_SUCCEEDED", json.dumps(final, indent=1))
    flown = [(s.get("behavior"), s.get("cause")) for s in final["steps"]]
    t.assertIn(("FOLLOW_PATH", "TERMINATION_CAUSE_GOAL_ACHIEVED"), flown)
    t.assertEqual(flown[-1], ("LAND", "TERMINATION_CAUSE_GOAL_ACHIEVED"))


def _plan(reply):
    return [(s["kind"], s["behavior"]) for s in reply["plan"]]


def _check_dry_run(t, out, err, ids):
    (reply,) = json_objects(out)
    t.assertNotIn("activationId", reply.get("activation", {}))
    plan = _plan(reply)
    t.assertIn(("KIND_ACTIVATE", "SELF_LOCALIZE_WITH_GROUND_TRUTH"), plan)
    t.assertEqual(plan[-1], ("KIND_ACTIVATE", "TAKE_OFF"))


def _check_coordinator_take_off(t, out, err, ids):
    (reply,) = json_objects(out)
    t.assertEqual(reply["system"], "basic_quadrotor_behaviors")
    t.assertTrue(reply["activation"].get("activationId"), reply)
    t.assertEqual(reply["activation"]["parameters"]["altitude_m"], 2.0)
    t.assertIn(("KIND_ACTIVATE", "SELF_LOCALIZE_WITH_GROUND_TRUTH"), _plan(reply))
    ids["coordinator_take_off"] = reply["activation"]["activationId"]


def _check_emergency_land(t, out, err, ids):
    (reply,) = json_objects(out)
    t.assertIn("EMERGENCY_LAND", reply.get("message", ""), reply)
    ids["emergency_land_wall_s"] = time.time()


def _check_fleet_events(t, out, err, ids):
    _check_deadline(t, err)
    replies = json_objects(out)
    t.assertIn("start", replies[0])
    events = _events(replies)
    t.assertEqual({e["behavior"] for e in events}, {"TAKE_OFF", "LAND"}, out)
    t.assertEqual([f["cause"] for f in _finished(events, ids["typed_take_off"])],
                  ["TERMINATION_CAUSE_GOAL_ACHIEVED"])
    # Emergency-landed while climbing (INTERRUPTED), or just after it got there.
    t.assertEqual(len(_finished(events, ids["coordinator_take_off"])), 1, out)
    lands = [e for e in events if e["behavior"] == "LAND" and "finished" in e]
    t.assertEqual([e["finished"]["cause"] for e in lands], ["TERMINATION_CAUSE_GOAL_ACHIEVED"])


SESSION = [
    Step(r"^grpcurl -plaintext \$COORDINATOR list$", _check_coordinator_list),
    Step(r"^grpcurl -plaintext \$BASIC list$", _check_system_list),
    Step(r"describe behaviorlib\.v1\.TakeOff$", _check_describe_service),
    Step(r"describe behaviorlib\.v1\.TakeOffParameters$", _check_describe_message),
    Step(r"\$BASIC behaviorlib\.v1\.BehaviorSystem/ListBehaviors$", _check_system_behaviors),
    Step(r"\$COORDINATOR behaviorlib\.v1\.Coordinator/ListBehaviors$", _check_fleet_behaviors),
    Step(r"Coordinator/CheckBehaviorSituation$", _check_not_feasible),
    Step(r"\$BASIC behaviorlib\.v1\.SelfLocalizeWithGroundTruth/Activate$",
         _check_localization_activated),
    Step(r"\$BASIC behaviorlib\.v1\.TakeOff/CheckSituation\b", _check_feasible, until=_feasible),
    Step(r"altitude_m\": 1\.5.*\$BASIC behaviorlib\.v1\.TakeOff/Activate$", _check_typed_take_off),
    Step(r"-max-time \d+ .*\$BASIC behaviorlib\.v1\.BehaviorSystem/WatchEvents$",
         _check_system_events, exit_code=STATUS_CODE_OFFSET + 4),
    Step(r"SELF_LOCALIZE_WITH_GROUND_TRUTH.*Coordinator/DeactivateBehavior$", _check_deactivated),
    Step(r"Coordinator/StartMission$", _check_mission_started),
    Step(r"-max-time \d+ .*Coordinator/WatchMission$", _check_mission_watched),
    Step(r"\"dry_run\": true.*Coordinator/ActivateBehavior$", _check_dry_run),
    Step(r"^(?!.*dry_run).*TAKE_OFF.*Coordinator/ActivateBehavior$", _check_coordinator_take_off),
    Step(r"Coordinator/EmergencyLand$", _check_emergency_land),
    Step(r"-max-time \d+ .*Coordinator/WatchEvents$", _check_fleet_events,
         exit_code=STATUS_CODE_OFFSET + 4),
]


# --- the test ----------------------------------------------------------------------

class ReadmeGrpcurlTest(unittest.TestCase):
    def setUp(self):
        self.temp = tempfile.mkdtemp(prefix="readme-grpcurl-e2e-")
        self.run_dir = os.path.join(self.temp, "run")
        self.launcher = None
        self.recorder = None
        self.clients = []
        # `grpcurl` for the README's commands: this file's runner.
        shim_dir = os.path.join(self.temp, "bin")
        os.makedirs(shim_dir)
        shim = os.path.join(shim_dir, "grpcurl")
        with open(shim, "w") as f:
            f.write(f"#!/bin/sh\nexec {shlex.quote(sys.executable)} "
                    f"{shlex.quote(os.path.abspath(__file__))} --grpcurl \"$@\"\n")
        os.chmod(shim, 0o755)
        self.env = dict(os.environ, PATH=f"{shim_dir}:{os.environ.get('PATH', '/usr/bin:/bin')}")
        with open(README) as f:
            self.readme = f.read()

    def tearDown(self):
        # Never leave a process behind, even when a step failed.
        if self.recorder is not None:
            self.recorder.stop()
        for client in self.clients:
            client.close()
        if self.launcher is not None and self.launcher.poll() is None:
            self.launcher.send_signal(signal.SIGINT)  # stops the stack in order
            try:
                output = self.launcher.communicate(timeout=40)[0]
                print(output[-3000:])
            except subprocess.TimeoutExpired:
                self.launcher.kill()
                self.launcher.wait()
        kill_launched(self.run_dir)
        shutil.rmtree(self.temp, ignore_errors=True)

    def _ports(self, name):
        ports = {}
        with open(os.path.join(self.run_dir, "ports", name + ".ports")) as f:
            for line in f:
                key, _, value = line.strip().partition("=")
                ports[key] = value
        return f"127.0.0.1:{ports['grpc_port']}"

    def _start_stack(self, setup):
        """The README's launcher line, with this build, a temporary run
        directory and --time-scale 2; waits until it serves."""
        lines = [line for line in setup if "deploy/local/launch.py" in line]
        self.assertEqual(len(lines), 1, "one launcher line in the set-up block")
        words = shlex.split(lines[0], comments=True)
        self.assertEqual(words[0], "deploy/local/launch.py")
        self.assertEqual(words[-1], "&", "the launcher runs in the background")
        self.assertNotIn("--demo", words)
        args = words[1:-1]
        self.assertIn("--build-dir", args)
        self.assertIn("--run-dir", args)
        args[args.index("--build-dir") + 1] = BUILD_DIR
        args[args.index("--run-dir") + 1] = self.run_dir
        self.launcher = subprocess.Popen(
            [sys.executable, LAUNCHER, *args, "--time-scale", TIME_SCALE], cwd=REPO,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        output = []
        deadline = time.monotonic() + 60
        for line in self.launcher.stdout:
            output.append(line)
            if "Ctrl-C stops everything." in line or time.monotonic() > deadline:
                break
        text = "".join(output)
        self.assertIn("Ctrl-C stops everything.", text, "the stack did not start:\n" + text)
        # The README says: ready when it prints this line (quoted there).
        self.assertIn('"Ctrl-C stops everything."', lines[0])
        return text

    def _addresses(self, setup, launcher_output):
        """COORDINATOR and BASIC as the README's set-up lines compute them
        (run by bash), checked against the launcher's own listing."""
        assignments = [line for line in setup if re.match(r"^[A-Z_]+=", line)]
        names = [line.split("=", 1)[0] for line in assignments]
        self.assertEqual(names, ["RUN", "COORDINATOR", "BASIC"])
        script = "\n".join(assignments[1:] + ['echo "$COORDINATOR $BASIC"'])
        result = subprocess.run(["bash", "-c", script], env=dict(self.env, RUN=self.run_dir),
                                capture_output=True, text=True, timeout=30)
        self.assertEqual(result.returncode, 0, result.stderr)
        coordinator, basic = result.stdout.split()
        self.assertEqual(coordinator, self._ports("coordinator"))
        self.assertEqual(basic, self._ports("basic_quadrotor_behaviors"))
        self.assertRegex(launcher_output, rf"coordinator +gRPC {re.escape(coordinator)} ")
        self.assertRegex(launcher_output,
                         rf"basic_quadrotor_behaviors +gRPC {re.escape(basic)} ")
        return coordinator, basic

    def _wait_for_systems(self, coordinator):
        """The launcher is ready once every process answers its health check;
        the systems' registration with the coordinator follows. A person
        typing the first commands would not notice; the test waits."""
        client = rpc.Client(coordinator, [demo.COORDINATOR])
        self.clients.append(client)
        demo.wait_for_systems(client, "drone1",
                              ["basic_quadrotor_behaviors", "quadrotor_motion_with_pid_control"])

    def _record_trajectory(self):
        client = rpc.Client(self._ports("simulator"), [demo.SIMULATOR])
        self.clients.append(client)
        self.recorder = demo.TrajectoryRecorder(client, "drone1")
        self.recorder.start()

    def _run(self, command, timeout_s):
        return subprocess.run(["bash", "-c", command], env=self.env, capture_output=True,
                              text=True, timeout=timeout_s)

    def test_readme_session(self):
        setup = readme_block(self.readme, "setup")
        session = shell_commands(readme_block(self.readme, "session"))
        for command in session:
            self.assertTrue(command.startswith("grpcurl "),
                            f"the session block holds grpcurl commands only: {command!r}")
        self.assertEqual(len(session), len(SESSION),
                         "the README's session and this test's steps differ in number")

        launcher_output = self._start_stack(setup)
        coordinator, basic = self._addresses(setup, launcher_output)
        self.env.update(COORDINATOR=coordinator, BASIC=basic)
        self._wait_for_systems(coordinator)
        self._record_trajectory()

        ids = {}
        for number, (command, step) in enumerate(zip(session, SESSION), start=1):
            # As the shell splits it (quotes and comments removed, variables
            # not expanded), on one line.
            one_line = re.sub(r"\s+", " ", " ".join(shlex.split(command, comments=True)))
            self.assertRegex(one_line, step.pattern, "README command out of order?")
            max_time = re.search(r"-max-time (\d+(?:\.\d*)?)", one_line)
            timeout_s = (float(max_time.group(1)) if max_time else 10.0) + 20.0
            started = time.monotonic()
            result = self._run(command, timeout_s)
            if step.until is not None:
                deadline = time.monotonic() + 15.0
                while (result.returncode == 0 and not step.until(result.stdout)
                       and time.monotonic() < deadline):
                    time.sleep(0.2)  # a state reached within seconds; no event to await
                    result = self._run(command, timeout_s)
            shown = re.sub(r"\s*\\?\n\s*", " ", command)
            print(f"\n[{number}] $ {shown}\n    exit {result.returncode} in "
                  f"{time.monotonic() - started:.1f} s\n{result.stdout[-1500:]}"
                  f"{result.stderr[-800:]}", flush=True)
            self.assertEqual(result.returncode, step.exit_code,
                             f"stdout:\n{result.stdout}\nstderr:\n{result.stderr}")
            step.check(self, result.stdout, result.stderr, ids)

        # The vehicle flew (both take-offs) and the emergency landing landed it.
        self.assertIn("emergency_land_wall_s", ids, "the session did not reach EmergencyLand")
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            samples = self.recorder.snapshot()
            if samples and samples[-1][4] == "FLIGHT_STATE_LANDED":
                break
            time.sleep(0.2)
        samples = self.recorder.snapshot()
        self.assertGreater(max(s[3] for s in samples), 1.4, "the vehicle never climbed")
        self.assertGreater(max(s[1] for s in samples), 1.8, "the mission's 2 m leg was not flown")
        self.assertEqual(samples[-1][4], "FLIGHT_STATE_LANDED", "not landed after EmergencyLand")
        self.assertLess(samples[-1][3], 0.2)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--grpcurl":
        sys.exit(grpcurl_main(sys.argv[2:]))
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=BUILD_DIR)
    cli_args, rest = parser.parse_known_args()
    BUILD_DIR = os.path.abspath(cli_args.build_dir)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)
