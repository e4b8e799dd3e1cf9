"""Errors of the behaviorlib client: every failed call raises an Error that
carries the gRPC status code, the server's message and, when the server sent
them, the google.rpc.Status details (`reason`, `metadata`,
`field_violations`).

    try:
        drone.take_off(altitude_m=100)
    except behaviorlib.InvalidArgument as error:
        print(error.code, error.message, error.field_violations)
"""

import re

import grpc
from google.rpc import error_details_pb2, status_pb2  # generated at install (setup.py)

# The trailing metadata key under which gRPC servers send a serialized
# google.rpc.Status with details.
STATUS_DETAILS_KEY = "grpc-status-details-bin"


class Error(Exception):
    """A call failed. `code` is the grpc.StatusCode, `message` the server's
    text; `reason` and `metadata` come from a google.rpc.ErrorInfo detail and
    `field_violations` (a list of (field, description)) from a
    google.rpc.BadRequest detail, when the server sent them."""

    def __init__(self, code, message, *, reason="", metadata=None, field_violations=(),
                 details=()):
        super().__init__(f"{code.name}: {message}")
        self.code = code
        self.message = message
        self.reason = reason
        self.metadata = dict(metadata or {})
        self.field_violations = list(field_violations)
        self.details = list(details)


class InvalidArgument(Error):
    """INVALID_ARGUMENT: a parameter, a mission file or a request is wrong."""


class NotFound(Error):
    """NOT_FOUND: no such robot, behavior, mission or belief."""


class AlreadyExists(Error):
    """ALREADY_EXISTS."""


class FailedPrecondition(Error):
    """FAILED_PRECONDITION: e.g. the behavior's situation does not allow it now."""


class Stale(FailedPrecondition):
    """FAILED_PRECONDITION with reason SAMPLE_STALE: the vehicle's newest
    sample is older than the call's limit (its metadata: topic, age_s,
    max_age_s)."""


class Aborted(Error):
    """ABORTED: e.g. the named activation is no longer the current one."""


class PermissionDenied(Error):
    """PERMISSION_DENIED: the caller's role may not make this call."""


class Unauthenticated(Error):
    """UNAUTHENTICATED."""


class ResourceExhausted(Error):
    """RESOURCE_EXHAUSTED: a cap was reached."""


class Unavailable(Error):
    """UNAVAILABLE: the server, or the system hosting the behavior, is down."""


class DeadlineExceeded(Error):
    """DEADLINE_EXCEEDED."""


class Cancelled(Error):
    """CANCELLED."""


_BY_CODE = {
    grpc.StatusCode.INVALID_ARGUMENT: InvalidArgument,
    grpc.StatusCode.NOT_FOUND: NotFound,
    grpc.StatusCode.ALREADY_EXISTS: AlreadyExists,
    grpc.StatusCode.FAILED_PRECONDITION: FailedPrecondition,
    grpc.StatusCode.ABORTED: Aborted,
    grpc.StatusCode.PERMISSION_DENIED: PermissionDenied,
    grpc.StatusCode.UNAUTHENTICATED: Unauthenticated,
    grpc.StatusCode.RESOURCE_EXHAUSTED: ResourceExhausted,
    grpc.StatusCode.UNAVAILABLE: Unavailable,
    grpc.StatusCode.DEADLINE_EXCEEDED: DeadlineExceeded,
    grpc.StatusCode.CANCELLED: Cancelled,
}


# Finer classes for some ErrorInfo reasons.
_BY_REASON = {"SAMPLE_STALE": Stale}


def error_class(code, reason=""):
    """The Error subclass raised for a grpc.StatusCode (and reason)."""
    return _BY_REASON.get(reason) or _BY_CODE.get(code, Error)


def _details(trailing_metadata):
    """The google.rpc.Status details of a reply's trailing metadata:
    (reason, metadata, field_violations, details). Empty when the server sent
    none (gRPC's own errors: deadlines, unreachable peers)."""
    raw = None
    for key, value in trailing_metadata or ():
        if key == STATUS_DETAILS_KEY:
            raw = value
    if raw is None:
        return "", {}, [], []
    status = status_pb2.Status()
    status.ParseFromString(raw)
    reason, metadata, violations, details = "", {}, [], []
    for any_detail in status.details:
        info = error_details_pb2.ErrorInfo()
        bad_request = error_details_pb2.BadRequest()
        if any_detail.Unpack(info):
            reason, metadata = info.reason, dict(info.metadata)
            details.append(info)
        elif any_detail.Unpack(bad_request):
            violations += [(v.field, v.description) for v in bad_request.field_violations]
            details.append(bad_request)
        else:
            details.append(any_detail)
    return reason, metadata, violations, details


# The access policy refuses a call inside gRPC's authentication layer, which
# sends only the code and the message: "<method> needs the role <role>;
# '<identity>' ..." (ROLE_REQUIRED in errors.proto).
_POLICY_REFUSAL = re.compile(r" needs the role ([^;]+); '(.*)'")


def _policy_refusal(code, message):
    """(reason, metadata) rebuilt from the access policy's refusal, or None."""
    if code != grpc.StatusCode.PERMISSION_DENIED:
        return None
    match = _POLICY_REFUSAL.search(message)
    if match is None:
        return None
    return "ROLE_REQUIRED", {"role": match.group(1), "identity": match.group(2)}


def from_rpc_error(error):
    """The Error for a grpc.RpcError (a sync or an asyncio one)."""
    code = error.code()
    message = error.details() or ""
    trailing = error.trailing_metadata()
    reason, metadata, violations, details = _details(trailing)
    if not reason:
        rebuilt = _policy_refusal(code, message)
        if rebuilt is not None:
            reason, metadata = rebuilt
    return error_class(code, reason)(code, message, reason=reason, metadata=metadata,
                             field_violations=violations, details=details)
