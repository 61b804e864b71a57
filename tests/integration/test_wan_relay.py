"""The WAN relay the many-host test and bench/multihost.py put between routers: it delivers
every byte, counts them per direction, and adds its delay each way."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time

import pytest

from tests.conftest import ROOT, free_port, wait_until

pytestmark = pytest.mark.integration


def _echo_server() -> tuple[socket.socket, int]:
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen()

    def serve() -> None:
        conn, _ = srv.accept()
        with conn:
            while data := conn.recv(65536):
                conn.sendall(data)

    threading.Thread(target=serve, daemon=True).start()
    return srv, srv.getsockname()[1]


def test_relay_delays_and_counts(tmp_path):
    srv, target = _echo_server()
    port, stats = free_port(), tmp_path / "relay.json"
    relay = subprocess.Popen([sys.executable, str(ROOT / "tests/integration/wan_relay.py"), "--listen", f"127.0.0.1:{port}",
                              "--target", f"127.0.0.1:{target}", "--delay-ms", "40", "--rate-mbit", "200",
                              "--stats", str(stats)])
    try:
        wait_until(stats.exists, 20, "the relay up")
        c = socket.create_connection(("127.0.0.1", port), timeout=20)
        t0 = time.monotonic()
        c.sendall(b"x")
        assert c.recv(1) == b"x"
        assert time.monotonic() - t0 >= 0.08, "a round trip through the relay took less than 2 x 40 ms"
        payload = bytes(range(256)) * 4096  # 1 MiB
        c.sendall(payload)
        got = b""
        while len(got) < len(payload):
            got += c.recv(1 << 20)
        assert got == payload
        c.close()
        want = {"up": len(payload) + 1, "down": len(payload) + 1}
        wait_until(lambda: {k: json.loads(stats.read_text())[k] for k in want} == want, 20, f"the relay counting {want}")
    finally:
        relay.terminate()
        relay.wait(20)
        srv.close()
