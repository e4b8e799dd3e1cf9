"""The audit log of a Python behavior system: a port of services/server_kit/audit_log.cc
(decision 24), so that a Python system's log reads as a C++ system's, line for line.

Every control call (any method that needs more than the viewer role) with who made it, what it
was and how it ended, and every call the access policy refused, one JSON object per line,
appended and flushed per record; also counted in behaviorlib_audited_calls_total{identity,
method, outcome}, whether or not there is a file (--audit-log empty: the metric only).

    {"time":"2026-11-27T02:10:00.123Z","identity":"behaviorlib:operator",
     "method":"/behaviorlib.v1.BehaviorSystem/ActivateBehavior","outcome":"OK","message":""}

The strings are escaped as protobuf's JSON printer escapes them in C++ (< and > as \\u003c and
\\u003e among others), and text with bytes past ASCII is C-escaped first, losslessly, as there.
The log rotates by size: when the file passes max_bytes it becomes FILE.1 (FILE.1 becomes
FILE.2, ...; the oldest past `keep` is removed) and a new FILE is begun (--audit-log-max-bytes,
--audit-log-keep), so that it takes at most (keep + 1) * max_bytes plus one record of disk.
"""

import datetime
import os
import sys
import threading

import grpc
from prometheus_client import Counter

from .parameters import StatusError

DEFAULT_MAX_BYTES = 64 << 20
DEFAULT_KEEP = 4
# A refused call may name any path: only our methods (shorter than this) are label values.
_MAX_LABEL = 128

# protobuf's JSON escapes of ASCII (util/internal/json_escaping.cc).
_JSON_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\f": "\\f", "\n": "\\n", "\r": "\\r",
                 "\t": "\\t", "<": "\\u003c", ">": "\\u003e", "\x7f": "\\u007f"}
# absl::CHexEscape of the bytes it escapes by name.
_C_ESCAPES = {ord("\n"): "\\n", ord("\r"): "\\r", ord("\t"): "\\t", ord('"'): '\\"',
              ord("'"): "\\'", ord("\\"): "\\\\"}
_HEX_DIGITS = "0123456789abcdefABCDEF"


def _c_hex_escape(data):
    """absl::CHexEscape: a hex digit right after a \\x escape is escaped too, so that it does
    not read as part of it."""
    out = []
    after_hex = False
    for byte in data:
        named = _C_ESCAPES.get(byte)
        if named is not None:
            out.append(named)
            after_hex = False
        elif byte < 0x20 or byte >= 0x7f or (after_hex and chr(byte) in _HEX_DIGITS):
            out.append(f"\\x{byte:02x}")
            after_hex = True
        else:
            out.append(chr(byte))
            after_hex = False
    return "".join(out)


def json_string(text):
    """`text` as a JSON string literal, escaped as the C++ audit log escapes it."""
    data = text.encode("utf-8", "surrogateescape")
    if any(byte >= 0x80 for byte in data):
        text = _c_hex_escape(data)
    out = []
    for c in text:
        escaped = _JSON_ESCAPES.get(c)
        if escaped is None and c < " ":
            escaped = f"\\u{ord(c):04x}"
        out.append(escaped or c)
    return '"' + "".join(out) + '"'


def _now_utc():
    """Wall time, to the millisecond: an audit log is read against other logs and clocks."""
    now = datetime.datetime.now(datetime.timezone.utc)
    return now.strftime("%Y-%m-%dT%H:%M:%S.") + f"{now.microsecond // 1000:03d}Z"


class AuditLog:
    """Appends audit records to `path` (made if missing; "": the metric only), counted in
    `registry`. StatusError INVALID_ARGUMENT for a max_bytes of 0, a negative keep, or a file
    that cannot be opened."""

    def __init__(self, path, registry, max_bytes=DEFAULT_MAX_BYTES, keep=DEFAULT_KEEP):
        if max_bytes <= 0 or keep < 0:
            raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                              "the audit log's rotation needs a size above 0 bytes and a count "
                              "of 0 or more files")
        self.path = path
        self._max_bytes = max_bytes
        self._keep = keep
        self._lock = threading.Lock()
        self._file = None
        self._bytes = 0
        if path:
            try:
                self._file = open(path, "ab")
            except OSError as error:
                raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                                  f"cannot open the audit log {path}: {error.strerror}") from error
            self._bytes = os.fstat(self._file.fileno()).st_size
        # Labels in the order prometheus-cpp prints them, so that the lines are the C++ ones.
        self._calls = Counter("behaviorlib_audited_calls_total",
                              "Control calls and refused calls, by method, outcome (gRPC code) "
                              "and caller identity", ("identity", "method", "outcome"),
                              registry=registry)

    def record(self, identity, method, outcome, message):
        """One control call's outcome, or a refusal: `outcome` is the gRPC code's name."""
        known = len(method) < _MAX_LABEL and method.startswith(("/behaviorlib.", "/grpc."))
        self._calls.labels(identity[:_MAX_LABEL], method if known else "other", outcome).inc()
        line = (f'{{"time":{json_string(_now_utc())},"identity":{json_string(identity)},'
                f'"method":{json_string(method)},"outcome":{json_string(outcome)},'
                f'"message":{json_string(message)}}}\n').encode("ascii")
        with self._lock:
            if self._file is None:
                return
            self._file.write(line)
            self._file.flush()
            self._bytes += len(line)
            if self._bytes >= self._max_bytes:
                self._rotate()

    def _rotate(self):
        self._file.close()
        self._file = None
        try:
            if self._keep == 0:
                os.remove(self.path)
            else:
                for i in range(self._keep - 1, 0, -1):
                    if os.path.exists(f"{self.path}.{i}"):
                        os.replace(f"{self.path}.{i}", f"{self.path}.{i + 1}")
                os.replace(self.path, f"{self.path}.1")
        except OSError as error:
            print(f"audit log: cannot rotate {self.path}: {error.strerror}; it goes on growing",
                  file=sys.stderr, flush=True)
        try:
            self._file = open(self.path, "ab")
        except OSError as error:
            print(f"audit log: cannot reopen {self.path}: {error.strerror}; control calls are "
                  "only counted", file=sys.stderr, flush=True)
            return
        self._bytes = os.fstat(self._file.fileno()).st_size

    def close(self):
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None
