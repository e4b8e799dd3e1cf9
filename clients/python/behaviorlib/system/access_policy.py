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

The file is read with a reader of the YAML that policies are written in, because this package
depends on nothing beyond grpcio and protobuf: block mappings and sequences, flow sequences and
mappings on one line ([viewer, operator], {robot: drone1, name: x}), plain, 'single' and
"double" quoted scalars, comments. What else YAML has (anchors and aliases, tags, block
scalars, values spanning lines, several documents) is refused with the file and line, never
read differently: a policy the C++ servers read with yaml-cpp in another way would give another
process other roles. Every refusal of the file's content names the file and line, in the words
of the C++ servers.
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


class Role(enum.Enum):
    """The roles, in the C++ order (std::set<Role> lists them so)."""
    VIEWER = "viewer"
    OPERATOR = "operator"
    SAFETY = "safety"
    SYSTEM = "system"
    ADMIN = "admin"


_ROLE_ORDER = list(Role)
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
    """"viewer, operator" (in the roles' order), or "no role"."""
    names = [role.value for role in _ROLE_ORDER if role in roles]
    return ", ".join(names) if names else "no role"


class Identity:
    """Who a certificate name or a token is: a name for logs, roles, and the robot (and
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
        return cls.parse(read_file_capped(path, MAX_POLICY_BYTES), path)

    @classmethod
    def parse(cls, text, file):
        """The policy written in `text`; StatusError INVALID_ARGUMENT "FILE:LINE: what"."""
        return cls(_entries(_read_yaml(text, file), file))

    def identify(self, certificate_names, bearer_token=""):
        """The Identity of a caller from its bearer token (when it sends one: a wrong token is
        not made good by the certificate) or the names of its certificate; None when the policy
        knows none of them."""
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
    with open(fd, "rb") as f:
        info = os.fstat(f.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise refused("not a regular file")
        if info.st_size > max_bytes:
            raise refused(f"{info.st_size} bytes, more than the {max_bytes} allowed")
        try:
            data = f.read(max_bytes + 1)
        except OSError as error:
            raise refused(f"cannot read: {error.strerror}") from error
    if len(data) > max_bytes:  # it grew after the stat
        raise refused(f"more than the {max_bytes} bytes allowed")
    return data
