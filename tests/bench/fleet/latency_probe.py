#!/usr/bin/python3
"""Cross-host delivery latency on the fleet's data path (radio_bench.py runs
it; decision 39).

    publish   inside a vehicle's host (ip netns exec): publishes --count
              samples at --rate-hz on --topic to --channel (the host's
              broker, or on the single-broker path the ground's broker
              through the radio's relay); each sample is a
              google.protobuf.Timestamp of the machine's wall clock when
              it was published.
    follow    anywhere: subscribes to --topic on --channel (the ground's
              broker) and prints one JSON line: the delays, in seconds, from
              each sample's stamp to its arrival, in arrival order.

Both ends read the same machine's clock (the hosts are namespaces of one
machine), so the delay is one way.
"""

import argparse
import json
import os
import sys
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(os.path.dirname(HERE)))
sys.path.insert(0, os.path.join(REPO, "deploy", "local"))

import rpc  # noqa: E402

CHANNEL = "behaviorlib.v1.DataChannel"
TIMESTAMP_URL = "type.googleapis.com/google.protobuf.Timestamp"


def publish(channel, topic, count, rate_hz):
    client = rpc.Client(channel, [CHANNEL])
    request_class = rpc.rc.message_class(client.pool, "behaviorlib.v1.PublishRequest")
    response_class = rpc.rc.message_class(client.pool, "behaviorlib.v1.PublishResponse")
    stamp_class = rpc.rc.message_class(client.pool, "google.protobuf.Timestamp")
    call = client.channel.stream_unary(f"/{CHANNEL}/Publish",
                                       request_serializer=lambda m: m.SerializeToString(),
                                       response_deserializer=response_class.FromString)

    left = [count]
    period = 1.0 / rate_hz
    next_at = [time.monotonic()]

    def samples():
        while left[0] > 0:
            now_ns = time.time_ns()
            request = request_class(topic=topic)
            request.sample.type_url = TIMESTAMP_URL
            request.sample.value = stamp_class(seconds=now_ns // 10**9,
                                               nanos=now_ns % 10**9).SerializeToString()
            left[0] -= 1
            yield request
            next_at[0] += period
            time.sleep(max(0.0, next_at[0] - time.monotonic()))

    # As a vehicle's publishers do, it publishes again on a new stream when
    # the server ended the last (a lost link) and goes on from where it was.
    accepted = 0
    while left[0] > 0:
        try:
            accepted += call(samples(), timeout=left[0] / rate_hz + 30).accepted_count
        except rpc.grpc.RpcError:
            time.sleep(period)
            next_at[0] = time.monotonic()
    client.close()
    return accepted


class Follower:
    """Subscribes to `topic` and records each sample's delay."""

    def __init__(self, channel, topic):
        self.client = rpc.Client(channel, [CHANNEL])
        self.stamp_class = rpc.rc.message_class(self.client.pool, "google.protobuf.Timestamp")
        self.call = self.client.stream(CHANNEL, "Subscribe", {
            "topic": topic, "mode": "DELIVERY_MODE_QUEUE", "queue_size": 1024})
        self.delays_s = []
        self.arrivals = []  # time.monotonic() of each
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        try:
            for response in self.call:
                arrived_ns = time.time_ns()
                self.arrivals.append(time.monotonic())
                stamp = self.stamp_class.FromString(response.sample.value)
                sent_ns = stamp.seconds * 10**9 + stamp.nanos
                self.delays_s.append((arrived_ns - sent_ns) / 1e9)
        except rpc.grpc.RpcError:
            pass

    def stop(self):
        self.call.cancel()
        self.thread.join(timeout=5)
        self.client.close()
        return self.delays_s


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("mode", choices=("publish", "follow"))
    parser.add_argument("--channel", required=True)
    parser.add_argument("--topic", required=True)
    parser.add_argument("--count", type=int, default=200)
    parser.add_argument("--rate-hz", type=float, default=5.0)
    parser.add_argument("--seconds", type=float, default=10.0, help="follow: for how long")
    args = parser.parse_args()
    if args.mode == "publish":
        print(publish(args.channel, args.topic, args.count, args.rate_hz))
        return 0
    follower = Follower(args.channel, args.topic)
    time.sleep(args.seconds)
    print(json.dumps(follower.stop()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
