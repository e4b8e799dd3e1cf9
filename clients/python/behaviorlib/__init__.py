"""behaviorlib: fly robots through the behaviorlib coordinator from Python.

    from behaviorlib import Fleet                  # synchronous
    from behaviorlib import aio                    # asyncio: aio.Fleet
    from behaviorlib import numpy_helpers          # position(pose), yaw(pose), ...

The gRPC stubs of the whole API are behaviorlib.v1.*_pb2 and *_pb2_grpc,
generated from the repository's proto/ when the package is built.
"""

from behaviorlib._core import BehaviorSpec, EventCursor, Parameter, Termination, mission_state
from behaviorlib.client import Activation, Beliefs, Fleet, Missions, Robot, Samples
from behaviorlib.errors import (Aborted, AlreadyExists, Cancelled, DeadlineExceeded, Error,
                                FailedPrecondition, InvalidArgument, NotFound, PermissionDenied,
                                ResourceExhausted, Stale, Unauthenticated, Unavailable)

__all__ = [
    "Aborted", "Activation", "AlreadyExists", "BehaviorSpec", "Beliefs", "Cancelled",
    "DeadlineExceeded", "Error", "EventCursor", "FailedPrecondition", "Fleet", "InvalidArgument",
    "Missions", "NotFound", "Parameter", "PermissionDenied", "ResourceExhausted", "Robot",
    "Samples", "Stale", "Termination", "Unauthenticated", "Unavailable", "mission_state",
]
