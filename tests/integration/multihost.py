"""Three hosts on one machine (network namespaces, :mod:`tests.integration.netns`), used by
tests/integration/test_multihost.py and bench/multihost.py:

* ``central``: the central router, the replay, the learner and the evaluator;
* ``a`` and ``b``: a host router (deploy/zenoh/host-router.json5, ``zenrl router --connect``)
  and ``actors_per_host`` actors connected to it.

Each host router reaches the central router through its own WAN relay
(tests/integration/wan_relay.py, in the central host): the one link between that host and the
central one, with an added delay and a bandwidth cap, whose bytes are counted. The test process
itself watches the run through a Unix socket of the central router (no network of its own).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from tests.integration.netns import NetHosts

ROOT = Path(__file__).resolve().parents[2]
RELAY = ROOT / "tests" / "integration" / "wan_relay.py"
ROUTER_PORT = 7447
RELAY_PORT = {"a": 7501, "b": 7502}


def router_config_file(src: Path, out: Path) -> Path:
    """``src`` (a deploy/zenoh router config) with shared memory and plugins off, as JSON: the
    hosts share one kernel, and shared memory would carry payloads past the counted links."""
    import zenoh

    cfg = zenoh.Config.from_file(str(src))
    cfg.insert_json5("transport/shared_memory/enabled", "false")
    cfg.insert_json5("plugins", "{}")
    out.write_text(str(cfg))
    return out


class Watch:
    """What the test process sees at the central router: weights broadcasts (count, bytes,
    newest version), each actor's latest stats and when they came, each actor's weights lag
    (newest version here minus the version the actor acts with, when its stats arrive: an upper
    bound, as the stats took the link's delay to come), eval returns, learner stats."""

    def __init__(self, node: Any, keys: Any) -> None:
        from zenrl.common import protocol as P

        self._P = P
        self.lock = threading.Lock()
        self.weights_n = 0
        self.weights_bytes = 0
        self.weights_version = -1
        self.actor_lags: list[int] = []
        self.actors: dict[str, tuple[float, dict]] = {}
        self.learner: dict = {}
        self.evals: list[float] = []
        node.subscribe(keys.weights, self._on_weights)
        node.subscribe(keys.stats_all, self._on_stats)
        node.subscribe(keys.eval, self._on_eval)

    def _on_weights(self, _key: str, payload: bytes) -> None:
        version = self._P.Weights.decode(payload).version
        with self.lock:
            self.weights_n += 1
            self.weights_bytes += len(payload)
            self.weights_version = max(self.weights_version, version)

    def _on_stats(self, _key: str, payload: bytes) -> None:
        m = self._P.Stats.decode(payload)
        with self.lock:
            if m.role == "actor":
                self.actors[m.id] = (time.monotonic(), dict(m.values))
                if self.weights_version >= 0 and m.values.get("policy_version", -1) >= 0:
                    self.actor_lags.append(self.weights_version - int(m.values["policy_version"]))
            elif m.role == "learner":
                self.learner = dict(m.values)

    def _on_eval(self, _key: str, payload: bytes) -> None:
        m = self._P.EvalResult.decode(payload)
        with self.lock:
            self.evals.append(float(m.returns.mean()))

    def actor(self, ident: str) -> tuple[float, dict]:
        with self.lock:
            return self.actors.get(ident, (0.0, {}))

    def weights(self) -> tuple[int, int]:
        with self.lock:
            return self.weights_n, self.weights_bytes


class ThreeHosts:
    """The layout of the module docstring; start with :meth:`start`, stop with :meth:`close`
    (also on failure: every process is killed, every namespace deleted)."""

    def __init__(self, tmp: Path, run_id: str, config: str, sets: list[str], actors_per_host: int = 2,
                 delay_ms: float = 25.0, rate_mbit: float = 100.0, evaluator: bool = True) -> None:
        self.tmp, self.run_id, self.config, self.sets = tmp, run_id, config, sets
        self.actors_per_host, self.delay_ms, self.rate_mbit, self.evaluator = actors_per_host, delay_ms, rate_mbit, evaluator
        self.net = NetHosts(["central", "a", "b"])
        self.procs: dict[str, subprocess.Popen] = {}
        self.sock = tmp / "central.sock"
        self.node: Any = None
        self.watch: Watch | None = None

    # -- processes ----------------------------------------------------------------------------
    def _start(self, name: str, host: str, argv: list[str]) -> subprocess.Popen:
        log = open(self.tmp / f"{name}.log", "ab")
        # PYTHONFAULTHANDLER: a process that hangs can be made to print every thread's stack
        # (SIGABRT; see dump_stacks)
        p = subprocess.Popen(self.net.cmd(host, [sys.executable, *argv]), stdout=log, stderr=subprocess.STDOUT, cwd=ROOT,
                             env=dict(os.environ, PYTHONFAULTHANDLER="1"))
        self.procs[name] = p
        return p

    def _zenrl(self, name: str, host: str, args: list[str]) -> subprocess.Popen:
        return self._start(name, host, ["-m", "zenrl.cli", *args])

    def log(self, name: str) -> str:
        p = self.tmp / f"{name}.log"
        return p.read_text(errors="replace")[-3000:] if p.exists() else ""

    def role_args(self, router: str) -> list[str]:
        out = ["--config", self.config, "--run-id", self.run_id, "--router", router,
               "--set", f"runs_dir={self.tmp / 'runs'}"]
        for s in self.sets:
            out += ["--set", s]
        return out

    def start_host_router(self, host: str) -> subprocess.Popen:
        central = self.net.addr["central"]
        return self._zenrl(f"router-{host}", host, [
            "router", "--router-config", str(self.host_cfg), "--listen", f"tcp/127.0.0.1:{ROUTER_PORT}",
            "--connect", f"tcp/{central}:{RELAY_PORT[host]}", "--log-level", "WARNING"])

    def actor_ids(self, host: str) -> list[str]:
        return [f"{host}{i}" for i in range(self.actors_per_host)]

    def start(self) -> "ThreeHosts":
        from zenrl.common import protocol as P
        from zenrl.common.transport import Node

        self.net.__enter__()
        self.central_cfg = router_config_file(ROOT / "deploy/zenoh/router.json5", self.tmp / "central-router.json")
        self.host_cfg = router_config_file(ROOT / "deploy/zenoh/host-router.json5", self.tmp / "host-router.json")
        central = self.net.addr["central"]
        self._zenrl("router-central", "central", [
            "router", "--router-config", str(self.central_cfg), "--listen", f"tcp/0.0.0.0:{ROUTER_PORT}",
            "--listen", f"unixsock-stream/{self.sock}", "--log-level", "WARNING"])
        for h in ("a", "b"):
            self._start(f"relay-{h}", "central", [
                str(RELAY), "--listen", f"{central}:{RELAY_PORT[h]}", "--target", f"127.0.0.1:{ROUTER_PORT}",
                "--delay-ms", str(self.delay_ms), "--rate-mbit", str(self.rate_mbit),
                "--stats", str(self.tmp / f"relay-{h}.json")])
            self.start_host_router(h)
        local = f"tcp/127.0.0.1:{ROUTER_PORT}"
        self._zenrl("replay", "central", ["replay", *self.role_args(local)])
        self._zenrl("learner", "central", ["learner", *self.role_args(local)])
        if self.evaluator:
            self._zenrl("evaluator", "central", ["evaluator", *self.role_args(local)])
        for h in ("a", "b"):
            for ident in self.actor_ids(h):
                self._zenrl(f"actor-{ident}", h, ["actor", "--id", ident, *self.role_args(local)])
        deadline = time.monotonic() + 60
        while not self.sock.exists():  # the central router is up (else Zenoh logs each retry)
            if time.monotonic() > deadline or self.procs["router-central"].poll() is not None:
                raise RuntimeError(f"the central router did not come up: {self.log('router-central')}")
            time.sleep(0.05)
        self.node = Node(f"unixsock-stream/{self.sock}", 30.0)
        self.watch = Watch(self.node, P.Keys(self.run_id))
        return self

    def relay(self, host: str) -> dict:
        p = self.tmp / f"relay-{host}.json"
        return json.loads(p.read_text()) if p.exists() else {"up": 0, "down": 0, "connections": 0, "open": 0}

    def cpu_s(self, name: str) -> float:
        """CPU seconds (user + system) used so far by process ``name`` (``ip netns exec``
        execs the command, so the pid is the process's own)."""
        fields = Path(f"/proc/{self.procs[name].pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def dump_stacks(self, names: list[str]) -> str:
        """Make ``names`` print every thread's stack into their logs (SIGABRT with
        PYTHONFAULTHANDLER; they die of it) and return the logs' tails: for a diagnosis."""
        for n in names:
            if self.procs[n].poll() is None:
                os.kill(self.procs[n].pid, signal.SIGABRT)
        for n in names:
            try:
                self.procs[n].wait(10)
            except subprocess.TimeoutExpired:
                pass
        return "\n".join(f"===== {n}\n{self.log(n)}" for n in names)

    def dead(self) -> list[str]:
        return [n for n, p in self.procs.items() if p.poll() is not None]

    def close(self) -> None:
        if self.node is not None:
            self.node.close()
            self.node = None
        # the roles first, while their routers still run (a role whose router is gone waits on
        # its session when it closes), then the routers and relays
        roles = [p for n, p in self.procs.items() if not n.startswith(("router-", "relay-", "replay"))]
        replay = [p for n, p in self.procs.items() if n == "replay"]
        links = [p for n, p in self.procs.items() if n.startswith(("router-", "relay-"))]
        for group in (roles, replay, links):
            for p in group:
                if p.poll() is None:
                    p.terminate()
            deadline = time.monotonic() + 20
            for p in group:
                try:
                    p.wait(max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        self.net.close()
