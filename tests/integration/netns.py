"""Hosts on one machine: Linux network namespaces joined by veth pairs to a bridge that lives in
a namespace of its own, so nothing is added to the machine's own network (no interface, route
or address outside the namespaces made here). Needs root and ``ip`` (iproute2).

    with NetHosts(["central", "a", "b"]) as net:
        net.addr["a"]                      # 10.77.0.2
        net.cmd("a", [python, "-m", ...])  # argv that runs inside host a

Namespace names carry a random id, so two runs never meet; :meth:`close` deletes every
namespace made (with it the veths and the bridge), also after a failure half-way."""

from __future__ import annotations

import os
import shutil
import subprocess
import uuid


class NetnsUnavailable(RuntimeError):
    """Network namespaces cannot be made here (not root, no iproute2, no CAP_NET_ADMIN)."""


def _ip(*args: str) -> None:
    p = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    if p.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {p.stderr.strip()}")


class NetHosts:
    def __init__(self, hosts: list[str], subnet: str = "10.77.0") -> None:
        self.tag = uuid.uuid4().hex[:8]
        self.hosts = list(hosts)
        self.ns = {h: f"zr{self.tag}{h[:4]}" for h in self.hosts}
        self.switch = f"zr{self.tag}sw"
        self.addr = {h: f"{subnet}.{i + 1}" for i, h in enumerate(self.hosts)}
        self._made: list[str] = []

    @staticmethod
    def check() -> None:
        """Raise :class:`NetnsUnavailable` with the reason when namespaces cannot be made."""
        if os.geteuid() != 0:
            raise NetnsUnavailable("network namespaces need root")
        if shutil.which("ip") is None:
            raise NetnsUnavailable("iproute2 (`ip`) is not installed")
        probe = f"zrprobe{uuid.uuid4().hex[:6]}"
        try:
            _ip("netns", "add", probe)
        except RuntimeError as e:
            raise NetnsUnavailable(f"cannot create a network namespace: {e}") from None
        _ip("netns", "del", probe)

    def __enter__(self) -> "NetHosts":
        try:
            self._up()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _add_ns(self, name: str) -> None:
        _ip("netns", "add", name)
        self._made.append(name)
        _ip("-n", name, "link", "set", "lo", "up")

    def _up(self) -> None:
        self._add_ns(self.switch)
        _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", self.switch, "link", "set", "br0", "up")
        for i, h in enumerate(self.hosts):
            ns = self.ns[h]
            self._add_ns(ns)
            port = f"p{i}"
            # both ends are created inside their namespaces: nothing appears in the caller's
            _ip("link", "add", "eth0", "netns", ns, "type", "veth", "peer", "name", port, "netns", self.switch)
            _ip("-n", self.switch, "link", "set", port, "master", "br0")
            _ip("-n", self.switch, "link", "set", port, "up")
            _ip("-n", ns, "addr", "add", f"{self.addr[h]}/24", "dev", "eth0")
            _ip("-n", ns, "link", "set", "eth0", "up")

    def cmd(self, host: str, argv: list[str]) -> list[str]:
        """``argv`` run inside ``host`` (``ip netns exec`` execs it: signals reach it directly)."""
        return ["ip", "netns", "exec", self.ns[host], *argv]

    def close(self) -> None:
        for name in reversed(self._made):
            subprocess.run(["ip", "netns", "del", name], capture_output=True, timeout=30)
        self._made.clear()
