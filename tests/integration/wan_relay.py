"""A userspace TCP relay that models a WAN link between two Zenoh routers (the kernels these
tests run on have no netem): every byte is delivered ``--delay-ms`` after it left, through a
link of ``--rate-mbit`` (serialisation time len/rate, one direction at a time), and counted.

    python tests/integration/wan_relay.py --listen 10.77.0.1:17447 --target 127.0.0.1:7447 \
        --delay-ms 25 --rate-mbit 100 --stats /tmp/relay.json

``--stats`` is rewritten (atomically) every 100 ms with the bytes delivered in each direction:
``{"up": client -> target, "down": target -> client, "connections": n, "open": n}``. Each
accepted connection gets its own link of ``--rate-mbit`` per direction. SIGTERM stops it.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import sys

CHUNK = 65536
QUEUE_CHUNKS = 64  # what a link holds in flight before the reader stops (TCP back-pressure)


class Relay:
    def __init__(self, target: tuple[str, int], delay_s: float, rate_bps: float | None) -> None:
        self.target = target
        self.delay_s = delay_s
        self.rate_Bps = None if not rate_bps else rate_bps / 8.0
        self.bytes = {"up": 0, "down": 0}
        self.connections = 0
        self.open = 0

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, direction: str) -> None:
        loop = asyncio.get_running_loop()
        q: asyncio.Queue = asyncio.Queue(QUEUE_CHUNKS)

        async def read() -> None:
            link_free = 0.0
            try:
                while True:
                    data = await reader.read(CHUNK)
                    if not data:
                        break
                    now = loop.time()
                    # the link sends one chunk after the other at the rate, then it travels
                    sent = max(now, link_free) + (len(data) / self.rate_Bps if self.rate_Bps else 0.0)
                    link_free = sent
                    await q.put((sent + self.delay_s, data))
            except (ConnectionError, OSError):
                pass
            await q.put(None)

        async def write() -> None:
            try:
                while True:
                    item = await q.get()
                    if item is None:
                        break
                    due, data = item
                    wait = due - loop.time()
                    if wait > 0:
                        await asyncio.sleep(wait)
                    writer.write(data)
                    await writer.drain()
                    self.bytes[direction] += len(data)
            except (ConnectionError, OSError):
                pass
            finally:
                writer.close()

        await asyncio.gather(read(), write())

    async def handle(self, c_reader: asyncio.StreamReader, c_writer: asyncio.StreamWriter) -> None:
        try:
            t_reader, t_writer = await asyncio.open_connection(*self.target)
        except OSError:
            c_writer.close()
            return
        self.connections += 1
        self.open += 1
        try:
            await asyncio.gather(self._pump(c_reader, t_writer, "up"), self._pump(t_reader, c_writer, "down"))
        finally:
            self.open -= 1

    def snapshot(self) -> dict:
        return {**self.bytes, "connections": self.connections, "open": self.open}


def _hostport(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit():
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    return host.strip("[]"), int(port)


async def amain(args: argparse.Namespace) -> None:
    relay = Relay(args.target, args.delay_ms / 1000.0, args.rate_mbit * 1e6 if args.rate_mbit else None)
    server = await asyncio.start_server(relay.handle, *args.listen)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)

    def dump() -> None:
        if args.stats:
            tmp = f"{args.stats}.tmp"
            with open(tmp, "w") as f:
                json.dump(relay.snapshot(), f)
            os.replace(tmp, args.stats)

    dump()
    while not stop.is_set():
        try:
            await asyncio.wait_for(stop.wait(), 0.1)
        except asyncio.TimeoutError:
            pass
        dump()
    server.close()
    dump()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--listen", type=_hostport, required=True, help="HOST:PORT to accept on")
    p.add_argument("--target", type=_hostport, required=True, help="HOST:PORT to forward to")
    p.add_argument("--delay-ms", type=float, default=0.0, help="one-way delay added in each direction")
    p.add_argument("--rate-mbit", type=float, default=0.0, help="bandwidth of each direction (0: unlimited)")
    p.add_argument("--stats", help="JSON file of the byte counters, rewritten every 100 ms")
    asyncio.run(amain(p.parse_args(argv)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
