"""Shared fixtures: a real in-process Zenoh router on a free loopback port, unique run ids, and
helpers to start zenrl roles as OS processes and wait on conditions with deadlines."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Callable

import pytest

ROOT = Path(__file__).resolve().parent.parent


def own_process_group() -> dict:
    """``subprocess.Popen`` arguments for a child in a process group of its own, in this session
    (a signal to the group reaches it and its children, as a terminal's Ctrl-C does; a new
    session would also put it in a scheduler autogroup of its own, which starves the test's
    other commands while it runs)."""
    return {"process_group": 0} if sys.version_info >= (3, 11) else {"preexec_fn": os.setpgrp}


def free_port() -> int:
    from zenrl.launcher import free_port as fp

    return fp()


def zenrl_pids(run_id: str, role: str | None = None, ident: str | None = None) -> list[int]:
    """Pids of live ``python -m zenrl.cli <role> ... --run-id <run_id>`` processes (from /proc,
    whose command lines are never truncated)."""
    pids = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            args = (d / "cmdline").read_bytes().decode(errors="replace").split("\0")
            if (d / "stat").read_text().split()[2] == "Z":
                continue
        except OSError:
            continue
        if "zenrl.cli" not in args or "--run-id" not in args:
            continue
        i = args.index("zenrl.cli")
        if args[args.index("--run-id") + 1] != run_id or i + 1 >= len(args) or args[i + 1] == "run":
            continue
        if role is not None and args[i + 1] != role:
            continue
        if ident is not None and not ("--id" in args and args[args.index("--id") + 1] == ident):
            continue
        pids.append(int(d.name))
    return sorted(pids)


def replay_stats_reader(node, keys) -> Callable[[], dict | None]:
    """``get()`` -> the newest stats values the replay service published (None if none new)."""
    from zenrl.common import protocol as P

    latest = node.subscribe_latest(keys.stats("replay", "replay"))

    def get():
        raw = latest.take()
        return None if raw is None else P.Stats.decode(raw).values

    return get


def wait_until(cond: Callable[[], object], timeout_s: float, what: str, interval_s: float = 0.1):
    """Poll ``cond`` until it returns something truthy; fail naming ``what`` at the deadline."""
    deadline = time.monotonic() + timeout_s
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(interval_s)


def run_zenrl(tmp_path: Path, config: str, run_id: str, *sets: str, extra_args: tuple[str, ...] = (),
              timeout_s: float = 900) -> tuple[subprocess.CompletedProcess, Path, dict[str, str]]:
    """``zenrl run --config CONFIG`` to completion on a free port with runs under ``tmp_path``;
    ``sets`` are ``section.field=value`` overrides. Returns (process, run dir, log tails)."""
    cmd = [sys.executable, "-m", "zenrl.cli", "run", "--config", config, "--run-id", run_id, "--no-progress",
           "--set", f"runs_dir={tmp_path}", "--set", f"transport.listen=[tcp/127.0.0.1:{free_port()}]",
           *extra_args]
    for s in sets:
        cmd += ["--set", s]
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout_s)
    run_dir = tmp_path / run_id
    logs = {f.name: f.read_text()[-3000:] for f in (run_dir / "logs").glob("*.log")}
    return p, run_dir, logs


@pytest.fixture
def router():
    """A real Zenoh router (in this process) on a free port; yields its client endpoint."""
    from zenrl.common.transport import open_router

    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    session = open_router([ep])
    yield ep
    session.close()


@pytest.fixture
def run_id():
    return f"t{uuid.uuid4().hex[:10]}"


class Procs:
    """Starts OS processes and makes sure they are gone after the test."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, args: list[str], env: dict | None = None) -> subprocess.Popen:
        log = open(self.tmp / f"{name}.log", "ab")
        p = subprocess.Popen([sys.executable, *args], stdout=log, stderr=subprocess.STDOUT, cwd=ROOT,
                             env=dict(os.environ, **(env or {})))
        self.procs.append((name, p))
        return p

    def zenrl(self, name: str, args: list[str], env: dict | None = None) -> subprocess.Popen:
        return self.start(name, ["-m", "zenrl.cli", *args], env)

    def log(self, name: str) -> str:
        p = self.tmp / f"{name}.log"
        return p.read_text(errors="replace") if p.exists() else ""

    def stop_all(self) -> None:
        for _, p in self.procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for name, p in self.procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
                raise AssertionError(f"{name} did not stop on SIGTERM within 20 s (hung)")


@pytest.fixture
def procs(tmp_path):
    ps = Procs(tmp_path)
    yield ps
    ps.stop_all()



@pytest.fixture
def tmpfs(tmp_path):
    """``mount(size)``: a real tmpfs of ``size`` (a disk that fills up) under ``tmp_path``,
    unmounted after the test; skips where it cannot be mounted (not root)."""
    mounted: list[Path] = []

    def mount(size: str) -> Path:
        d = tmp_path / f"disk{len(mounted)}"
        d.mkdir()
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(d)], capture_output=True)
        if r.returncode:
            pytest.skip(f"cannot mount a tmpfs (needs root): {r.stderr.decode().strip()}")
        mounted.append(d)
        return d

    yield mount
    for d in mounted:
        subprocess.run(["umount", "-l", str(d)], check=False)


@pytest.fixture
def small_disk(tmpfs):
    """A real 4 MiB tmpfs."""
    return tmpfs("4m")
