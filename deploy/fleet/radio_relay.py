#!/usr/bin/python3
"""A TCP relay that delays what it carries: the latency of a vehicle's radio
link in the fleet on one machine (deploy/fleet/fleet.py). The kernel here has
no netem qdisc, so the delay is added by this relay, which the fleet puts on
every connection that crosses a vehicle's radio link; iptables' statistic
match drops packets (loss), tbf bounds the bandwidth, and a veth set down cuts
the link (decision 39).

    radio_relay.py --map 127.0.0.1:7422=10.77.0.1:7422 \\
                   --map 10.77.0.11:60061=127.0.0.1:50061 --delay-ms 30 --jitter-ms 10

Each direction of each connection holds every chunk it reads for the delay,
plus or minus a uniformly drawn jitter, and never releases a chunk before the
one read before it (TCP keeps its order). It reads no more while 1 MiB waits
in a direction (flow control). A connection that the far side cannot take is
closed; one side's end closes the other's after what was read has gone.
"""

import argparse
import asyncio
import random
import signal
import sys
import time

CHUNK = 64 * 1024
MAX_HELD = 1 << 20


def address(text):
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit():
        raise argparse.ArgumentTypeError(f"'{text}' is not HOST:PORT")
    return host, int(port)


def mapping(text):
    listen, sep, target = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"'{text}' is not LISTEN_HOST:PORT=TO_HOST:PORT")
    return address(listen), address(target)


class Direction:
    """One direction of one connection: read, hold for the delay, write.
    `carried` ([bytes]) counts what it wrote."""

    def __init__(self, reader, writer, delay_s, jitter_s, rng, carried):
        self.reader, self.writer = reader, writer
        self.delay_s, self.jitter_s, self.rng = delay_s, jitter_s, rng
        self.held = asyncio.Queue()
        self.held_bytes = 0
        self.room = asyncio.Event()
        self.room.set()
        self.last_release = 0.0
        self.carried = carried

    async def read(self):
        try:
            while True:
                await self.room.wait()
                data = await self.reader.read(CHUNK)
                jitter = self.rng.uniform(-self.jitter_s, self.jitter_s) if self.jitter_s else 0.0
                release = max(self.last_release, time.monotonic() + self.delay_s + jitter)
                self.last_release = release
                self.held_bytes += len(data)
                if self.held_bytes >= MAX_HELD:
                    self.room.clear()
                await self.held.put((release, data))
                if not data:
                    return
        except (ConnectionError, OSError):
            await self.held.put((time.monotonic(), b""))

    async def write(self):
        try:
            while True:
                release, data = await self.held.get()
                wait = release - time.monotonic()
                if wait > 0:
                    await asyncio.sleep(wait)
                self.held_bytes -= len(data)
                if self.held_bytes < MAX_HELD:
                    self.room.set()
                if not data:
                    if self.writer.can_write_eof():
                        self.writer.write_eof()
                    return
                self.writer.write(data)
                self.carried[0] += len(data)
                await self.writer.drain()
        except (ConnectionError, OSError):
            pass


async def relay(client_reader, client_writer, target, options, rng, counts):
    try:
        server_reader, server_writer = await asyncio.wait_for(
            asyncio.open_connection(*target), timeout=10.0)
    except (OSError, asyncio.TimeoutError):
        client_writer.close()
        return
    up = Direction(client_reader, server_writer, options.delay_s, options.jitter_s, rng, counts[0])
    down = Direction(server_reader, client_writer, options.delay_s, options.jitter_s, rng,
                     counts[1])
    await asyncio.gather(up.read(), up.write(), down.read(), down.write(),
                         return_exceptions=True)
    for writer in (client_writer, server_writer):
        writer.close()


async def main(options):
    rng = random.Random(options.seed)
    servers = []
    counts = {}  # per mapping: bytes relayed towards the target, and back
    for listen, target in options.map:
        counts[(listen, target)] = ([0], [0])

        async def handle(reader, writer, target=target, mapped=counts[(listen, target)]):
            await relay(reader, writer, target, options, rng, mapped)
        servers.append(await asyncio.start_server(handle, *listen, reuse_address=True))
    print(f"radio_relay: {len(servers)} relays, delay {options.delay_s * 1e3:g} ms "
          f"+- {options.jitter_s * 1e3:g} ms", file=sys.stderr, flush=True)
    if options.ready_file:
        with open(options.ready_file, "w") as f:
            f.write("ready\n")
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, stop.set)
    await stop.wait()
    for server in servers:
        server.close()
    for (listen, target), (up, down) in counts.items():
        print(f"radio_relay: {listen[0]}:{listen[1]} -> {target[0]}:{target[1]}: {up[0]} bytes "
              f"there, {down[0]} back", file=sys.stderr, flush=True)


def parse(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--map", type=mapping, action="append", required=True,
                        metavar="LISTEN=TO", help="relay LISTEN_HOST:PORT to TO_HOST:PORT")
    parser.add_argument("--delay-ms", type=float, default=30.0, help="added to each direction")
    parser.add_argument("--jitter-ms", type=float, default=10.0,
                        help="each chunk's delay is drawn uniformly within +- this")
    parser.add_argument("--seed", type=int, default=1, help="of the jitter draws")
    parser.add_argument("--ready-file", default="", help="written once every relay listens")
    options = parser.parse_args(argv)
    if options.delay_ms < 0 or options.jitter_ms < 0 or options.jitter_ms > options.delay_ms:
        parser.error("--delay-ms and --jitter-ms must be >= 0, the jitter at most the delay")
    options.delay_s = options.delay_ms / 1e3
    options.jitter_s = options.jitter_ms / 1e3
    return options


if __name__ == "__main__":
    asyncio.run(main(parse()))
