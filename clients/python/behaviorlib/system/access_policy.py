"""Roles of a Python behavior system: a port of services/server_kit/access_policy.cc (decision
24), so that one --access-policy file gives a Python system's callers the roles, and refuses
them the calls, that it gives and refuses at a C++ system.

    policy = AccessPolicy.load("policy.yaml")            # StatusError INVALID_ARGUMENT
    identity = policy.identify(["behaviorlib:operator"], bearer_token="")
    required_role("/behaviorlib.v1.BehaviorSystem/ActivateBehavior")   # Role.OPERATOR
    caller = caller_of(context, policy)                  # in a handler: who called
    refusal = robot_scope_of(context, policy).permits("drone1", "activate behaviors")

The file (YAML) maps identities to roles:

    identities:
      - certificate: behaviorlib:operator          # a client certificate's URI or DNS SAN,
        roles: [viewer, operator, safety]          #   or its CN
      - certificate: behaviorlib:drone1-my-behaviors
        roles: [viewer, operator, system]
        system: {robot: drone1, name: my_behaviors}
      - certificate: behaviorlib:drone1-tablet     # an operator of one robot
        roles: [viewer, operator]
        robot: drone1
      - token_sha256: 5e884898da28...              # a bearer token, by its SHA-256
        name: dashboard                            #   (authorization: Bearer <token>)
        roles: [viewer]

Each method needs one role, by its name (required_role): viewer for List*, Watch*, Check*, Get*,
Read*, Subscribe*, health and reflection; safety for EmergencyLand and Kill; system for
RegisterSystem, Heartbeat, UnregisterSystem and FollowTime; admin for the simulator's Reset,
SetTimeScale, Step and InjectFailure; operator for everything else, methods unknown included.
An identity bound to a robot (`system: {robot}` or `robot:`) commands only that robot: a
behavior system refuses its lifecycle calls for another (RobotScope, ROBOT_NOT_PERMITTED).

The file is read with Debian's python3-yaml (PyYAML's composer, whose nodes keep their lines),
as the C++ servers read it with yaml-cpp. Every refusal of the file's content names the file and
line, in the words of the C++ servers where they refuse it too (the parsers' own words for what
is not YAML differ).
"""

import enum
import hashlib
import hmac
import os
import stat

import grpc

from behaviorlib.v1 import errors_pb2

from .parameters import StatusError

# The largest policy file read (access_policy.cc AccessPolicy::load).
MAX_POLICY_BYTES = 1 << 20
# The certificate properties a caller is named by, in the order identify() tries them.
_CERTIFICATE_PROPERTIES = ("peer_uri", "peer_dns", "x509_common_name")
_IDENTITY_KEYS = ("certificate", "token_sha256", "name", "roles", "system", "robot")
_HEX = "0123456789abcdef"


class Role(enum.Enum):
    """The roles, in the C++ order (std::set<Role> lists them so)."""
    VIEWER = "viewer"
    OPERATOR = "operator"
    SAFETY = "safety"
    SYSTEM = "system"
    ADMIN = "admin"


_ROLE_ORDER = list(Role)
_ROLES_BY_NAME = {role.value: role for role in Role}
_VIEWER_PREFIXES = ("List", "Watch", "Check", "Get", "Read", "Subscribe")


def required_role(method):
    """The Role that `method` ("/package.Service/Method") needs (requiredRole)."""
    slash = method.rfind("/")
    service = method[:slash] if slash >= 0 else ""
    name = method[slash + 1:] if slash >= 0 else method
    if service.startswith(("/grpc.health.", "/grpc.reflection.")):
        return Role.VIEWER
    if service == "/behaviorlib.v1.Simulator" and name in ("Reset", "SetTimeScale", "Step",
                                                          "InjectFailure"):
        return Role.ADMIN
    if name in ("RegisterSystem", "Heartbeat", "UnregisterSystem", "FollowTime"):
        return Role.SYSTEM
    if name in ("EmergencyLand", "Kill"):
        return Role.SAFETY
    if name.startswith(_VIEWER_PREFIXES):
        return Role.VIEWER
    return Role.OPERATOR


def roles_text(roles):
    """The roles' names in the C++ order ("viewer, operator"), or "no role"."""
    names = [role.value for role in _ROLE_ORDER if role in roles]
    return ", ".join(names) if names else "no role"


class Identity:
    """Who a certificate name or a token is: a name for logs, its roles, and the robot (and
    system) it is bound to ("" for none)."""

    def __init__(self, name, roles, robot_id="", system=""):
        self.name = name
        self.roles = frozenset(roles)
        self.robot_id = robot_id
        self.system = system


class AccessPolicy:
    """The identities of a policy file, each named by a certificate or a token's SHA-256."""

    def __init__(self, entries):
        # [(certificate, token_sha256, Identity)]: one of the first two is "".
        self._entries = list(entries)

    def __len__(self):
        return len(self._entries)

    @classmethod
    def load(cls, path):
        """The policy in the file at `path`; StatusError INVALID_ARGUMENT naming the file (and
        the line, for its content)."""
        text = read_file_capped(path, MAX_POLICY_BYTES).decode("utf-8", "surrogateescape")
        return cls.parse(text, path)

    @classmethod
    def parse(cls, text, file):
        """The policy written in `text`; StatusError INVALID_ARGUMENT "FILE:LINE: what"."""
        return cls(_entries(_document(text, file), file))

    def identify(self, certificate_names, bearer_token=""):
        """The Identity of a caller from its bearer token (when it sends one: a wrong token is
        not made good by the certificate) or the names of its certificate (URI and DNS SANs,
        then CN); None when the policy knows none of them."""
        if bearer_token:
            digest = hashlib.sha256(bearer_token.encode("utf-8", "surrogateescape")).hexdigest()
            for _, token_sha256, identity in self._entries:
                if token_sha256 and hmac.compare_digest(token_sha256, digest):
                    return identity
            return None
        for name in certificate_names:
            for certificate, _, identity in self._entries:
                if certificate and certificate == name:
                    return identity
        return None


def _entries(root, file):
    """[(certificate, token_sha256, Identity)] of a policy document (AccessPolicy::parse)."""
    def error(node, what):
        return StatusError(grpc.StatusCode.INVALID_ARGUMENT, f"{file}:{node.line}: {what}")

    def text(node):
        # yaml-cpp's as<std::string>(): a scalar's text, "null" for a null node.
        if node.kind == "scalar":
            return node.value
        if node.kind == "null":
            return "null"
        raise error(node, "bad conversion")

    identities = root.get("identities")
    if identities is None or identities.kind != "seq":
        raise error(root, "an access policy is a mapping with a list 'identities'")
    for key, _ in root.value:
        if key.value != "identities":
            raise error(key, f"unknown key '{key.value}' (expected identities)")
    entries = []
    for item in identities.value:
        if item.kind != "map":
            raise error(item, "an identity is a mapping")
        for key, _ in item.value:
            if key.value not in _IDENTITY_KEYS:
                raise error(key, f"unknown key '{key.value}' (expected certificate or "
                                 "token_sha256, name, roles, system, robot)")
        certificate = text(item.get("certificate")) if item.get("certificate") else ""
        token_sha256 = ""
        if item.get("token_sha256"):
            token_sha256 = text(item.get("token_sha256")).lower()
            if len(token_sha256) != 64 or any(c not in _HEX for c in token_sha256):
                raise error(item.get("token_sha256"), "token_sha256 must be 64 hex digits")
        if (certificate == "") == (token_sha256 == ""):
            raise error(item, "an identity has either a certificate or a token_sha256")
        if item.get("name"):
            name = text(item.get("name"))
        else:
            name = f"token {token_sha256[:8]}" if not certificate else certificate
        roles_node = item.get("roles")
        if roles_node is None or roles_node.kind != "seq" or not roles_node.value:
            raise error(item, "an identity needs a list of roles")
        roles = set()
        for role_node in roles_node.value:
            role_name = text(role_node)
            role = _ROLES_BY_NAME.get(role_name)
            if role is None:
                raise error(role_node, f"unknown role '{role_name}' (expected viewer, operator, "
                                       "safety, system, admin)")
            roles.add(role)
        robot_id, system = "", ""
        system_node = item.get("system")
        if system_node:
            if (system_node.kind != "map" or not system_node.get("robot")
                    or not system_node.get("name")):
                raise error(system_node, "system: {robot: ROBOT_ID, name: SYSTEM}")
            robot_id = text(system_node.get("robot"))
            system = text(system_node.get("name"))
        robot_node = item.get("robot")
        if robot_node:
            robot = robot_node.value if robot_node.kind == "scalar" else ""
            if not robot:
                raise error(robot_node, "robot: ROBOT_ID, the one robot it may command")
            if robot_id and robot_id != robot:
                raise error(robot_node, f"robot '{robot}' is not the system's robot '{robot_id}'")
            robot_id = robot
        if Role.SYSTEM in roles and not system:
            raise error(item, "the system role needs system: {robot, name}, the system it may "
                              "register as")
        entries.append((certificate, token_sha256, Identity(name, roles, robot_id, system)))
    return entries


# ---- Who called ----------------------------------------------------------------------------------

class Caller:
    """The caller of one call, identified as the role check identified it (callerOf)."""

    def __init__(self, name, identity=None, policy=False):
        self.identity = name  # the name logs and messages give it
        self.roles = identity.roles if identity else frozenset()
        self.robot_id = identity.robot_id if identity else ""
        self.system = identity.system if identity else ""
        self.policy = policy  # its roles come from an access policy


def certificate_names(context):
    """The names of the caller's certificate, in the order identify() tries them: URI SANs,
    DNS SANs, CN (none for a plaintext call)."""
    auth = context.auth_context() or {}
    return [value.decode("utf-8", "replace")
            for prop in _CERTIFICATE_PROPERTIES for value in auth.get(prop, ())]


def bearer_token(metadata):
    """The token of an `authorization: Bearer <token>` header among `metadata` (the last one,
    as gRPC's auth processor sees them), or ""."""
    token = ""
    for key, value in metadata or ():
        if key == "authorization":
            token = value[7:] if isinstance(value, str) and value[:7].lower() == "bearer " else ""
    return token


def caller_name(identity, names):
    """How logs and messages name a caller: its identity's name, else its certificate's first
    name, else "anonymous"."""
    if identity is not None:
        return identity.name
    return names[0] if names else "anonymous"


def caller_of(context, policy):
    """The Caller of a call under `policy` (None: no policy in force); None for a plaintext
    call without a policy."""
    names = certificate_names(context)
    if policy is None and not names:
        return None
    identity = (policy.identify(names, bearer_token(context.invocation_metadata()))
                if policy is not None else None)
    return Caller(caller_name(identity, names), identity, policy is not None)


def role_refusal(policy, method, names, token):
    """(who, refusal): the caller's name and, when `policy` does not give it the role that
    `method` needs, PERMISSION_DENIED ROLE_REQUIRED naming the role (the C++ Authorizer's
    message and details), else None."""
    identity = policy.identify(names, token)
    who = caller_name(identity, names)
    needed = required_role(method)
    if identity is not None and needed in identity.roles:
        return who, None
    has = ("is not in the access policy" if identity is None
           else f"has {roles_text(identity.roles)}")
    message = f"{method} needs the role {needed.value}; '{who}' {has}"
    return who, StatusError(grpc.StatusCode.PERMISSION_DENIED, message,
                            reason=errors_pb2.ROLE_REQUIRED,
                            metadata={"role": needed.value, "identity": who})


class RobotScope:
    """The one robot a caller may command (RobotScope): an identity bound to a robot by its
    `system: {robot}` or `robot:`; any other caller, and every caller without a policy, is
    unbound."""

    def __init__(self, identity="", robot_id=""):
        self.identity = identity
        self.robot_id = robot_id

    @property
    def bound(self):
        return bool(self.robot_id)

    def permits(self, robot_id, what):
        """None, or PERMISSION_DENIED ROBOT_NOT_PERMITTED when bound to another robot than
        `robot_id`; `what` names the call ("activate behaviors")."""
        if not self.bound or robot_id == self.robot_id:
            return None
        return StatusError(
            grpc.StatusCode.PERMISSION_DENIED,
            f"'{self.identity}' may {what} only for robot {self.robot_id}, not for robot "
            f"'{robot_id}'", reason=errors_pb2.ROBOT_NOT_PERMITTED,
            metadata={"identity": self.identity, "robot": robot_id,
                      "allowed_robot": self.robot_id})


def robot_scope_of(context, policy):
    """The RobotScope of a call's caller under `policy` (unbound without one)."""
    caller = caller_of(context, policy)
    if caller is None or not caller.policy:
        return RobotScope()
    return RobotScope(caller.identity, caller.robot_id)


# ---- The YAML of a policy file -------------------------------------------------------------------

class _Node:
    """A node of the document: kind "map" (value: [(key node, value node)]), "seq" (value:
    [node]), "scalar" (value: str) or "null"; `line` counts from 1."""

    __slots__ = ("kind", "value", "line")

    def __init__(self, kind, value, line):
        self.kind = kind
        self.value = value
        self.line = line

    def get(self, key):
        """The value of the first `key` of a mapping (yaml-cpp's node[key]), or None."""
        if self.kind != "map":
            return None
        return next((value for k, value in self.value if k.value == key), None)


# Deeper documents are refused (an alias may make a node its own child).
_MAX_DEPTH = 64
_NULL_TAG = "tag:yaml.org,2002:null"


def _document(text, file):
    """The policy document's root, composed by PyYAML (its nodes keep their lines);
    StatusError INVALID_ARGUMENT "FILE:LINE: what" for what is not one YAML document."""
    import yaml  # Debian's python3-yaml

    def refused(line, what):
        return StatusError(grpc.StatusCode.INVALID_ARGUMENT, f"{file}:{line}: {what}")

    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None) or getattr(error, "context_mark", None)
        problem = getattr(error, "problem", None) or str(error)
        raise refused(mark.line + 1 if mark else 1, f"not YAML: {problem}") from None

    def convert(node, depth):
        line = node.start_mark.line + 1
        if depth > _MAX_DEPTH:
            raise refused(line, f"nested more than {_MAX_DEPTH} deep")
        if isinstance(node, yaml.MappingNode):
            return _Node("map", [(convert(k, depth + 1), convert(v, depth + 1))
                                 for k, v in node.value], line)
        if isinstance(node, yaml.SequenceNode):
            return _Node("seq", [convert(v, depth + 1) for v in node.value], line)
        if node.tag == _NULL_TAG:
            return _Node("null", None, line)
        return _Node("scalar", node.value, line)

    if root is None:
        return _Node("null", None, 1)
    return convert(root, 0)


def read_file_capped(path, max_bytes):
    """The bytes of a regular file of at most `max_bytes` (confined_files.cc readFileCapped);
    StatusError INVALID_ARGUMENT "PATH: why" otherwise. Opened without blocking, so that a FIFO
    is refused instead of waited on."""
    def refused(why):
        return StatusError(grpc.StatusCode.INVALID_ARGUMENT, f"{path}: {why}")
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as error:
        raise refused(f"cannot open: {error.strerror}") from error
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise refused("not a regular file")
        if info.st_size > max_bytes:
            raise refused(f"{info.st_size} bytes, more than the {max_bytes} allowed")
        try:
            data = os.read(fd, max_bytes + 1)
        except OSError as error:
            raise refused(f"cannot read: {error.strerror}") from error
    finally:
        os.close(fd)
    if len(data) > max_bytes:  # it grew after the stat
        raise refused(f"more than the {max_bytes} bytes allowed")
    return data
