"""Transport security and the call guard of a Python behavior system: a port of
services/server_kit/transport_security.cc and of the part of server_runtime.cc that enforces
roles and writes the audit log (decisions 23 and 24), so that a Python system joins a
deployment that runs with mutual TLS and an access policy as a C++ system does.

    security = TransportSecurity(cert_file, key_file, ca_file, insecure=False)
    security.check_listen("0.0.0.0:50061")       # no TLS off loopback without --insecure
    security.load()                              # the PEM files, read and checked
    port = server.add_secure_port(address, security.server_credentials())
    channel = security.channel("127.0.0.1:50060", options)   # every client channel
    guard = CallGuard(policy, audit_log)         # the server's first interceptor

Transport. With --tls-cert, --tls-key and --tls-ca, the server requires a client certificate
that chains to the CA, and every channel the process opens (to the coordinator, the channel
broker, the simulator, a flight controller) presents this process's certificate and checks the
server's against the CA and the host it dials. The three files are read once, at start: a
missing flag, a file that cannot be read, that is larger than 1 MiB or that is not PEM stops
the start with the C++ message naming the flag. Without TLS the server binds only loopback,
unless --insecure accepts the risk. /metrics stays plain HTTP either way (decision 23).

Calls. gRPC Python has no auth metadata processor, so the C++ processor's check runs in a
server interceptor instead, as the first thing each call does, before any handler and before
the call is counted in grpc_server_* (as there): with a policy (it needs TLS), a caller
without the role a method needs is refused PERMISSION_DENIED ROLE_REQUIRED, the C++ message,
and the refusal is audited. Then every control call (a method that needs more than viewer) is
audited with its outcome once its handler is done. A method the process does not serve is
refused UNIMPLEMENTED with no message, as by the C++ servers, once the policy let the caller
call it. The C++ processor's refusal reaches its clients without the ErrorInfo it builds (gRPC's
auth filter hands on only the code and the message); this one carries it.
"""

import sys

import grpc

from . import _protocol
from .access_policy import (Role, bearer_token, caller_of, certificate_names,
                            read_file_capped, required_role, role_refusal)
from .parameters import StatusError

# The largest PEM file read (transport_security.cc kMaxPemBytes).
MAX_PEM_BYTES = 1 << 20
_SCHEMES = ("dns:///", "dns:", "ipv4:", "ipv6:")


def _read_pem(flag, path):
    if not path:
        raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                          f"TLS needs --tls-cert, --tls-key and --tls-ca; {flag} is missing")
    try:
        data = read_file_capped(path, MAX_PEM_BYTES)
    except StatusError as error:
        raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                          f"{flag} {path}: {error.message}") from error
    if b"-----BEGIN " not in data:
        raise StatusError(grpc.StatusCode.INVALID_ARGUMENT, f"{flag} {path}: not a PEM file")
    return data


def host_of(address):
    """The host part of "host:port", "[v6]:port", "dns:///host:port", "ipv4:host:port"."""
    for scheme in _SCHEMES:
        if address.startswith(scheme):
            address = address[len(scheme):]
            break
    if address.startswith("["):
        close = address.find("]")
        return address if close < 0 else address[1:close]
    colon = address.rfind(":")
    return address if colon < 0 else address[:colon]


def is_loopback_address(address):
    """True for 127.0.0.0/8, ::1, localhost and unix sockets."""
    if address.startswith(("unix:", "unix-abstract:")):
        return True
    host = host_of(address)
    return host in ("localhost", "::1") or host.startswith("127.")


class TransportSecurity:
    """The process's transport: mutual TLS from three PEM files, or plaintext (on loopback,
    unless `insecure`). Every server and channel of the process takes it from here."""

    def __init__(self, cert_file="", key_file="", ca_file="", insecure=False):
        self.cert_file = cert_file or ""
        self.key_file = key_file or ""
        self.ca_file = ca_file or ""
        self.insecure = insecure
        self._material = None
        self._channel_credentials = None

    @property
    def tls(self):
        return bool(self.cert_file or self.key_file or self.ca_file)

    def load(self):
        """Reads the three files (once); StatusError INVALID_ARGUMENT naming the flag: TLS needs
        all three, each a readable PEM file of at most 1 MiB. Nothing to read without TLS."""
        if not self.tls or self._material is not None:
            return
        self._material = (_read_pem("--tls-cert", self.cert_file),
                          _read_pem("--tls-key", self.key_file),
                          _read_pem("--tls-ca", self.ca_file))
        cert, key, ca = self._material
        self._channel_credentials = grpc.ssl_channel_credentials(
            root_certificates=ca, private_key=key, certificate_chain=cert)

    def check_listen(self, address, flag="--listen"):
        """StatusError INVALID_ARGUMENT when `address` is not loopback, without TLS and without
        --insecure; the message says what that would risk. With --insecure, a warning."""
        if self.tls or is_loopback_address(address):
            return
        if self.insecure:
            print(f"warning: {flag} {address} without TLS (--insecure): anyone who can reach "
                  "this port can command, land or kill the vehicles", file=sys.stderr, flush=True)
            return
        raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                          f"{flag} {address} is not a loopback address and there is no TLS: "
                          "anyone who could reach it could command, land or kill the vehicles. "
                          "Give --tls-cert, --tls-key and --tls-ca (scripts/make-dev-certs.sh), "
                          "or --insecure to accept that risk on a private network")

    def server_credentials(self):
        """Server credentials that require and verify a client certificate from the CA; None
        without TLS. After load()."""
        if not self.tls:
            return None
        cert, key, ca = self._material
        return grpc.ssl_server_credentials([(key, cert)], root_certificates=ca,
                                           require_client_auth=True)

    @property
    def channel_credentials(self):
        """The client credentials every channel of the process uses (this process's
        certificate, the CA); None without TLS. After load()."""
        return self._channel_credentials

    def channel(self, target, options=()):
        """A channel to `target` with the process's credentials: TLS with TLS, never
        plaintext in its place."""
        return open_channel(target, self._channel_credentials, options)


def open_channel(target, channel_credentials, options=()):
    """A grpc.Channel to `target`: TLS with `channel_credentials`, plaintext without."""
    if channel_credentials is not None:
        return grpc.secure_channel(target, channel_credentials, options=list(options))
    return grpc.insecure_channel(target, options=list(options))


# ---- The call guard ------------------------------------------------------------------------------

def _name_of(caller):
    return caller.identity if caller else "anonymous"


def _detail_text(details):
    if isinstance(details, bytes):
        return details.decode("utf-8", "replace")
    return details or ""


class CallGuard(grpc.ServerInterceptor):
    """Enforces `policy` (an AccessPolicy, or None: every caller may call anything) and hands
    every control call's outcome, and every refusal, to `audit` (an audit.AuditLog). Give it to
    the server first among its interceptors: a refused call then reaches no other."""

    def __init__(self, policy, audit):
        self._policy = policy
        self._audit = audit

    def _check(self, method, context):
        """Refuses the call (aborts it) when the policy does not give its caller the role."""
        if self._policy is None:
            return
        who, refusal = role_refusal(self._policy, method, certificate_names(context),
                                    bearer_token(context.invocation_metadata()))
        if refusal is not None:
            self._audit.record(who, method, refusal.code.name, refusal.message)
            _protocol.abort(context, refusal)

    def _record(self, method, context, default_code):
        code = context.code() or default_code
        self._audit.record(_name_of(caller_of(context, self._policy)), method, code.name,
                           _detail_text(context.details()))

    def intercept_service(self, continuation, handler_call_details):
        method = handler_call_details.method
        handler = continuation(handler_call_details)
        control = required_role(method) != Role.VIEWER
        if handler is None:
            def unknown(requests, context):
                self._check(method, context)
                if control:
                    self._audit.record(_name_of(caller_of(context, self._policy)), method,
                                       grpc.StatusCode.UNIMPLEMENTED.name, "")
                context.abort(grpc.StatusCode.UNIMPLEMENTED, "")
            return grpc.stream_stream_rpc_method_handler(unknown)
        if self._policy is None and not control:
            return handler
        streaming = (handler.request_streaming, handler.response_streaming)
        make, behavior = {
            (False, False): (grpc.unary_unary_rpc_method_handler, handler.unary_unary),
            (False, True): (grpc.unary_stream_rpc_method_handler, handler.unary_stream),
            (True, False): (grpc.stream_unary_rpc_method_handler, handler.stream_unary),
            (True, True): (grpc.stream_stream_rpc_method_handler, handler.stream_stream),
        }[streaming]
        if handler.response_streaming:
            def guarded(request, context):
                self._check(method, context)
                if not control:
                    yield from behavior(request, context)
                    return
                try:
                    yield from behavior(request, context)
                except GeneratorExit:
                    self._record(method, context, grpc.StatusCode.CANCELLED)
                    raise
                except BaseException:
                    self._record(method, context, grpc.StatusCode.UNKNOWN)
                    raise
                self._record(method, context, grpc.StatusCode.OK)
        else:
            def guarded(request, context):
                self._check(method, context)
                if not control:
                    return behavior(request, context)
                try:
                    response = behavior(request, context)
                except BaseException:
                    self._record(method, context, grpc.StatusCode.UNKNOWN)
                    raise
                self._record(method, context, grpc.StatusCode.OK)
                return response
        return make(guarded, request_deserializer=handler.request_deserializer,
                    response_serializer=handler.response_serializer)
