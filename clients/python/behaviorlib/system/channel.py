"""A client of the data channel (behaviorlib.v1.DataChannel) for Python behaviors: the topics a
behavior reads (the pose estimate, sensors) and writes (motion references), as
services/channel/channel_client.h gives them to C++ behaviors.

    channel = DataChannel("127.0.0.1:50051")
    channel.publish("robots/drone1/motion_reference", reference)   # a protobuf message
    channel.sync()                      # every sample published so far is taken by the broker
    pose = channel.get_latest("robots/drone1/self_localization/pose", PoseStamped)
    subscription = channel.subscribe("robots/drone1/self_localization/pose", PoseStamped,
                                     on_sample, latest_first=True)
    ...
    subscription.close()
    channel.close()

The deterministic mode's data barrier (time_follower.py) uses the rest, as the C++ follower uses
ChannelClient's acceptedSeqs(), delivered(), waitDelivered() and awaitedTopics():

    channel.sync(if_published=True)     # no round trip when nothing was published since the last
    channel.accepted_seqs()             # {topic: topic_seq of the last sample published there}
    channel.wait_delivered({"robots/drone1/ground_truth/pose": 42}, timeout_s=0.05)
    channel.awaited_topics()            # the topics wait_delivered() looks at

Publishing uses one PublishAcked stream per client, opened on first use and opened again after
sync() saw it fail (what was published on the failed stream after the refused sample is lost, as
with the C++ client's stream). sync() asks the stream
to answer once the broker took everything before: the deterministic mode's barrier, and how a
publisher learns that a refused sample ended its stream. A subscription is a reader thread that
calls its callback for each sample and subscribes again (backing off from 0.1 s to 2 s) when the
stream breaks, until closed; it stops for good only when the broker refuses the request itself
(INVALID_ARGUMENT: a bad topic name). Errors are parameters.StatusError with the broker's code and
message.

A subscription knows the topic_seq of the newest sample it has processed (its callback returned),
and counts from the broker's registration on (its initial metadata "behaviorlib-subscribed"
names the topic_seq the topic had then: samples before it never come). delivered() asks whether
every connected subscription that is not rate-limited has processed the samples a time grant
names; a disconnected one counts as done, as in the C++ client (it waits for no sample).
"""

import queue
import threading
import time

import grpc

from behaviorlib.system.parameters import StatusError
from behaviorlib.v1 import channel_pb2, channel_pb2_grpc

# Reconnection back-off of a subscription, seconds.
FIRST_RETRY_S = 0.1
MAX_RETRY_S = 2.0
# How long a sync() or get_latest() waits for the broker by default, seconds.
DEFAULT_TIMEOUT_S = 5.0
# Samples a publisher may have queued for its stream before publish() blocks (a bound on memory
# when the broker is slow or away).
MAX_QUEUED_SAMPLES = 1024
# The broker's initial metadata on a registered subscription: the topic's topic_seq then
# (services/channel/include/behaviorlib/channel/topic.h kSubscribedMetadataKey).
SUBSCRIBED_METADATA_KEY = "behaviorlib-subscribed"


def _status_error(error):
    """A grpc.RpcError as a StatusError with its code and message."""
    return StatusError(error.code(), error.details() or "")


class _PublishStream:
    """One PublishAcked stream: a request queue drained by gRPC's sender, and a reader thread
    that queues the replies to its sync requests, in order, then why the stream ended."""

    _END = object()

    def __init__(self, stub, metadata):
        self._requests = queue.Queue(maxsize=MAX_QUEUED_SAMPLES)
        self._replies = queue.Queue()
        self._call = stub.PublishAcked(iter(self._requests.get, self._END), metadata=metadata)
        self.broken = None  # the StatusError that ended it, once a sync saw it end
        threading.Thread(target=self._read, name="publish replies", daemon=True).start()

    def _read(self):
        try:
            for reply in self._call:
                self._replies.put(reply)
            self._replies.put(StatusError(grpc.StatusCode.UNAVAILABLE,
                                          "the broker ended the publish stream"))
        except grpc.RpcError as error:
            self._replies.put(_status_error(error))

    def put(self, request):
        self._requests.put(request)

    def next_reply(self, timeout_s):
        """The reply to the oldest unanswered sync request; raises StatusError when the stream
        ended (the broker refused a sample, or went away) or timeout_s passed."""
        try:
            reply = self._replies.get(timeout=timeout_s)
        except queue.Empty:
            self.close()
            self.broken = StatusError(grpc.StatusCode.DEADLINE_EXCEEDED,
                                      f"the broker did not answer a sync within {timeout_s} s")
            raise self.broken from None
        if isinstance(reply, StatusError):
            self.broken = reply
            raise reply
        return reply

    def close(self):
        self._call.cancel()
        try:
            self._requests.put_nowait(self._END)
        except queue.Full:
            pass


class Subscription:
    """A running subscription (DataChannel.subscribe): its reader thread calls the callback for
    every sample until close(). `on_progress` is called (on the reader thread) whenever
    processed_seq or connected changed: the channel's wait_delivered() wakes on it."""

    def __init__(self, stub, request, message_type, on_sample, on_error, metadata=(),
                 on_progress=None):
        self.topic = request.topic
        self._stub = stub
        self._metadata = metadata
        self._request = request
        self._message_type = message_type
        self._on_sample = on_sample
        self._on_error = on_error
        self._on_progress = on_progress
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._call = None
        self._connected = threading.Event()
        self.received = 0
        # The topic_seq of the newest sample whose callback returned, or that the broker's
        # registration said came before this subscription (0 before either).
        self.processed_seq = 0
        # Why the last stream ended (None while the first runs); final when the broker refused
        # the request (INVALID_ARGUMENT).
        self.status = None
        self._thread = threading.Thread(target=self._run, name=f"subscribe {self.topic}",
                                        daemon=True)
        self._thread.start()

    def wait_connected(self, timeout_s):
        """True once a stream is registered at the broker (from then on every sample published
        reaches this subscription)."""
        return self._connected.wait(timeout_s)

    @property
    def connected(self):
        """Whether a stream is registered at the broker now."""
        return self._connected.is_set()

    @property
    def rate_limited(self):
        """Read at a rate (max_rate_hz): it promises no particular sample, so delivered() does
        not wait for it."""
        return self._request.max_rate_hz > 0

    @property
    def closed(self):
        return self._closed.is_set()

    def _processed(self, topic_seq):
        if topic_seq > self.processed_seq:
            self.processed_seq = topic_seq
        self._progress()

    def _progress(self):
        if self._on_progress is not None:
            self._on_progress()

    def _run(self):
        delay = FIRST_RETRY_S
        while not self._closed.is_set():
            with self._lock:
                if self._closed.is_set():
                    return
                self._call = self._stub.Subscribe(self._request, metadata=self._metadata)
            try:
                # The broker sends its initial metadata once the subscription is registered,
                # naming the topic_seq that samples published before it had reached: those never
                # come (unless the latest is sent first), so delivered() must not wait for them.
                # A refused or failed call carries none of ours.
                registered = dict(self._call.initial_metadata() or ()).get(
                    SUBSCRIBED_METADATA_KEY)
                if registered is not None:
                    if registered.isdigit():
                        self.processed_seq = max(self.processed_seq, int(registered))
                    self._connected.set()
                    self._progress()
                for response in self._call:
                    delay = FIRST_RETRY_S
                    message = self._message_type()
                    if response.sample.Unpack(message):
                        self.received += 1
                        self._on_sample(message)
                    else:
                        self.status = StatusError(
                            grpc.StatusCode.FAILED_PRECONDITION,
                            f"{self.topic} carries {response.sample.type_url}, not "
                            f"{self._message_type.DESCRIPTOR.full_name}")
                        self._report(self.status)
                    self._processed(response.topic_seq)
                self.status = StatusError(grpc.StatusCode.UNAVAILABLE, "the stream ended")
            except grpc.RpcError as error:
                self.status = _status_error(error)
                if self._closed.is_set():
                    return
                if error.code() == grpc.StatusCode.INVALID_ARGUMENT:
                    self._report(self.status)
                    return
            finally:
                self._connected.clear()
                self._progress()
            if self._closed.wait(delay):
                return
            delay = min(delay * 2, MAX_RETRY_S)

    def _report(self, error):
        if self._on_error is not None:
            self._on_error(error)

    def close(self, timeout_s=5.0):
        """Ends the stream and joins the reader (not from inside the callback)."""
        with self._lock:
            self._closed.set()
            if self._call is not None:
                self._call.cancel()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout_s)


class DataChannel:
    """A connection to a channel broker ("host:port"); thread-safe. `channel_credentials`
    (grpc.ssl_channel_credentials) makes it TLS, `metadata` adds headers (a bearer token)."""

    def __init__(self, address, *, channel_credentials=None, metadata=()):
        self.address = address
        options = [("grpc.max_receive_message_length", 64 << 20)]
        self._channel = (grpc.secure_channel(address, channel_credentials, options)
                         if channel_credentials is not None
                         else grpc.insecure_channel(address, options))
        self._metadata = tuple(metadata)
        self._stub = channel_pb2_grpc.DataChannelStub(self._channel)
        self._lock = threading.Lock()
        self._stream = None
        # Something was published on the current stream since its last sync.
        self._unsynced = False
        # PublishResponse.topic_seqs of the syncs, merged (emptied when a stream failed: a
        # restarted broker numbers its topics anew). Locks of their own: a sync holds _lock for
        # its round trip, and the barrier's reads must not wait for it.
        self._accepted_lock = threading.Lock()
        self._accepted_seqs = {}
        self._subscriptions_lock = threading.Lock()
        self._subscriptions = []
        # Notified whenever a subscription processed a sample or (dis)connected.
        self._progress = threading.Condition()

    def _open_stream(self):
        if self._stream is None or self._stream.broken is not None:
            self._stream = _PublishStream(self._stub, self._metadata)
            self._unsynced = False
        return self._stream

    def publish(self, topic, message):
        """Publishes `message` on `topic`. Asynchronous: a sample the broker refuses (a wrong
        type for the topic) ends the stream, and sync() then raises why."""
        request = channel_pb2.PublishRequest(topic=topic)
        request.sample.Pack(message)
        with self._lock:
            self._open_stream().put(request)
            self._unsynced = True

    def sync(self, timeout_s=DEFAULT_TIMEOUT_S, *, if_published=False):
        """Returns the PublishResponse once the broker took every sample published so far (with
        each topic's last topic_seq, also merged into accepted_seqs()); StatusError when a
        sample was refused or the broker is away. The next publish() opens a new stream.
        With `if_published`, returns None at once when nothing was published since the last
        sync (the C++ ChannelClient::sync()'s skip: a time follower syncs once a grant)."""
        with self._lock:
            if if_published and not self._unsynced:
                return None
            stream = self._open_stream()
            stream.put(channel_pb2.PublishRequest(sync=True))
            try:
                reply = stream.next_reply(timeout_s)
            except StatusError:
                self._stream = None
                self._unsynced = False
                with self._accepted_lock:
                    self._accepted_seqs.clear()
                raise
            self._unsynced = False
            with self._accepted_lock:
                for topic, seq in reply.topic_seqs.items():
                    self._accepted_seqs[topic] = max(self._accepted_seqs.get(topic, 0), seq)
            return reply

    def accepted_seqs(self):
        """{topic: the topic_seq of the last sample this client published there}, as the broker
        answered the syncs so far; what a time follower's report names
        (FollowTimeRequest.topic_seqs)."""
        with self._accepted_lock:
            return dict(self._accepted_seqs)

    def _live_subscriptions(self):
        with self._subscriptions_lock:
            return [s for s in self._subscriptions if not s.closed]

    def delivered(self, topic_seqs):
        """Whether every connected subscription of this client that is not rate-limited has
        processed the sample numbered topic_seqs[its topic], or a later one (a topic not in the
        mapping, and a subscription not connected, count as done): the deterministic mode's
        data barrier, ChannelClient::delivered()."""
        for subscription in self._live_subscriptions():
            if not subscription.connected or subscription.rate_limited:
                continue
            if subscription.processed_seq < topic_seqs.get(subscription.topic, 0):
                return False
        return True

    def wait_delivered(self, topic_seqs, timeout_s):
        """Waits until delivered(topic_seqs) (True) or `timeout_s` passes (False); woken by the
        subscriptions' progress, not by polling."""
        deadline = time.monotonic() + timeout_s
        with self._progress:
            while not self.delivered(topic_seqs):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._progress.wait(remaining)
            return True

    def awaited_topics(self):
        """The topics delivered() looks at (its live subscriptions' that are not rate-limited,
        connected or not), sorted, each once: a time follower names them to the simulator, whose
        grants then name only theirs."""
        return sorted({s.topic for s in self._live_subscriptions() if not s.rate_limited})

    def _notify_progress(self):
        with self._progress:
            self._progress.notify_all()

    def get_latest(self, topic, message_type, timeout_s=DEFAULT_TIMEOUT_S):
        """The newest sample on `topic` as `message_type`; StatusError NOT_FOUND when nothing
        was published yet."""
        try:
            reply = self._stub.GetLatest(channel_pb2.GetLatestRequest(topic=topic),
                                         timeout=timeout_s, metadata=self._metadata)
        except grpc.RpcError as error:
            raise _status_error(error) from None
        message = message_type()
        if not reply.sample.sample.Unpack(message):
            raise StatusError(grpc.StatusCode.FAILED_PRECONDITION,
                              f"{topic} carries {reply.sample.sample.type_url}, not "
                              f"{message_type.DESCRIPTOR.full_name}")
        return message

    def subscribe(self, topic, message_type, on_sample, *, latest_first=False, max_rate_hz=0.0,
                  queue_size=0, on_error=None):
        """Calls on_sample(message) on a reader thread for each sample of `topic` (LATEST
        delivery, or QUEUE with queue_size > 0). on_error(StatusError) hears of a sample of
        another type and of a refused request. Returns the Subscription."""
        request = channel_pb2.SubscribeRequest(
            topic=topic, send_latest_first=latest_first, max_rate_hz=max_rate_hz,
            mode=(channel_pb2.DELIVERY_MODE_QUEUE if queue_size else
                  channel_pb2.DELIVERY_MODE_LATEST), queue_size=queue_size)
        subscription = Subscription(self._stub, request, message_type, on_sample, on_error,
                                    self._metadata, on_progress=self._notify_progress)
        with self._subscriptions_lock:
            self._subscriptions = [s for s in self._subscriptions if not s.closed]
            self._subscriptions.append(subscription)
        return subscription

    def close(self):
        """Ends the publish stream and every subscription, then the connection."""
        with self._subscriptions_lock:
            subscriptions, self._subscriptions = self._subscriptions, []
        with self._lock:
            stream, self._stream = self._stream, None
        for subscription in subscriptions:
            subscription.close()
        if stream is not None:
            stream.close()
        self._channel.close()
