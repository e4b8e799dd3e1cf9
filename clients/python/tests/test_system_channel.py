"""The Python behaviors' data-channel client (behaviorlib.system.channel) against the real
broker (build/bin/channel_broker on loopback, a port of its own): publish and sync, the newest
sample, subscriptions that resume after the broker restarts, and the broker's refusals."""

import os
import subprocess
import tempfile
import threading
import time

import grpc
import pytest

from behaviorlib.system.channel import DataChannel
from behaviorlib.system.parameters import StatusError
from behaviorlib.v1 import motion_pb2, types_pb2

from conftest import BUILD_DIR, wait_until

TOPIC = "robots/drone1/motion_reference"


class Broker:
    """build/bin/channel_broker on 127.0.0.1, restartable on the same port."""

    def __init__(self):
        self.directory = tempfile.mkdtemp(prefix="behaviorlib-channel-")
        self.port = 0
        self.process = None
        self.start()

    def start(self):
        port_file = os.path.join(self.directory, "broker.ports")
        if os.path.exists(port_file):
            os.remove(port_file)
        self.process = subprocess.Popen(
            [os.path.join(BUILD_DIR, "bin", "channel_broker"), "--listen",
             f"127.0.0.1:{self.port}", "--metrics_listen", "127.0.0.1:0", "--port_file",
             port_file], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

        def port():
            if not os.path.exists(port_file):
                return None
            with open(port_file) as f:
                fields = dict(line.strip().split("=") for line in f if "=" in line)
            return int(fields["grpc_port"]) if "grpc_port" in fields else None
        self.port = wait_until(port, 30, "the broker's port file")

    @property
    def address(self):
        return f"127.0.0.1:{self.port}"

    def stop(self):
        self.process.kill()
        self.process.wait(10)


@pytest.fixture
def broker():
    broker = Broker()
    yield broker
    broker.stop()


def reference(x):
    message = motion_pb2.MotionReference(source="CIRCLE_AROUND-test")
    message.header.robot_id = "drone1"
    message.point.position_m.x = x
    return message


def test_published_samples_are_taken_read_and_delivered(broker):
    channel = DataChannel(broker.address)
    try:
        with pytest.raises(StatusError) as empty:
            channel.get_latest(TOPIC, motion_pb2.MotionReference, timeout_s=2)
        assert empty.value.code == grpc.StatusCode.NOT_FOUND
        got = []
        arrived = threading.Event()

        def on_sample(message):
            got.append(message.point.position_m.x)
            if len(got) == 3:
                arrived.set()
        subscription = channel.subscribe(TOPIC, motion_pb2.MotionReference, on_sample,
                                         queue_size=10)
        assert subscription.wait_connected(10)
        for x in (1.0, 2.0, 3.0):
            channel.publish(TOPIC, reference(x))
        taken = channel.sync()
        assert taken.accepted_count == 3 and taken.topic_seqs[TOPIC] == 3
        assert channel.get_latest(TOPIC, motion_pb2.MotionReference).point.position_m.x == 3.0
        assert arrived.wait(10) and got == [1.0, 2.0, 3.0]
        subscription.close()
    finally:
        channel.close()


def test_a_refused_sample_is_told_by_sync_and_the_next_stream_works(broker):
    channel = DataChannel(broker.address)
    try:
        channel.publish(TOPIC, reference(1.0))
        assert channel.sync().accepted_count == 1
        # A topic carries one type for its whole life: a PoseStamped is refused.
        channel.publish(TOPIC, types_pb2.PoseStamped())
        with pytest.raises(StatusError) as refused:
            channel.sync()
        assert refused.value.code == grpc.StatusCode.INVALID_ARGUMENT, refused.value
        channel.publish(TOPIC, reference(2.0))
        assert channel.sync().accepted_count == 1  # a new stream
        with pytest.raises(StatusError) as bad_name:
            channel.publish("robots/drone1/bad topic", reference(1.0))
            channel.sync()
        assert bad_name.value.code == grpc.StatusCode.INVALID_ARGUMENT
    finally:
        channel.close()


def test_a_subscription_resumes_after_the_broker_restarts(broker):
    channel = DataChannel(broker.address)
    got = []
    try:
        subscription = channel.subscribe(TOPIC, motion_pb2.MotionReference,
                                         lambda m: got.append(m.point.position_m.x),
                                         latest_first=True)
        assert subscription.wait_connected(10)
        channel.publish(TOPIC, reference(1.0))
        channel.sync()
        wait_until(lambda: got == [1.0] or None, 10, "the first sample")
        broker.stop()
        broker.start()  # the same port
        wait_until(lambda: subscription.wait_connected(0.1) or None, 30, "resubscribed")
        # The first publish after the restart may meet the dead stream: sync tells.
        for _ in range(10):
            channel.publish(TOPIC, reference(2.0))
            try:
                channel.sync()
                break
            except StatusError:
                time.sleep(0.2)
        wait_until(lambda: got[-1] == 2.0 or None, 10, "a sample after the restart")
        subscription.close()
        assert not subscription._thread.is_alive()
    finally:
        channel.close()


def test_a_refused_subscription_stops_and_says_why(broker):
    channel = DataChannel(broker.address)
    errors = []
    try:
        subscription = channel.subscribe("robots/drone1/bad topic", motion_pb2.MotionReference,
                                         lambda m: None, on_error=errors.append)
        wait_until(lambda: errors or None, 10, "the refusal")
        assert errors[0].code == grpc.StatusCode.INVALID_ARGUMENT
        subscription._thread.join(10)
        assert not subscription._thread.is_alive()
    finally:
        channel.close()
