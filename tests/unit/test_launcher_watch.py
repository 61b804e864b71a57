"""The launcher's watch over processes it cannot hear from (zenrl/launcher/supervisor.py): an
actor that has published nothing since it started, and the launcher's own check of the env that
takes long. Real child processes; the launcher is not started."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time

import gymnasium as gym
import pytest

from zenrl.common.config import load_config
from zenrl.launcher.supervisor import Child, Launcher, catches_signal, check_env

#: a child with the stack-dump handler every zenrl role registers (zenrl/cli.py), then asleep
DUMPS = ("import faulthandler, signal, time; faulthandler.register(signal.SIGUSR1, all_threads=True); "
         "print('up', flush=True); time.sleep(120)")
#: a child without it: SIGUSR1 would kill it
PLAIN = "import time; print('up', flush=True); time.sleep(120)"


def _child(tmp_path, name: str, code: str) -> Child:
    log = tmp_path / f"{name}.log"
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=open(log, "wb"), text=True)
    assert p.stdout.readline().strip() == "up"
    return Child(name, "actor", [], proc=p, log_path=log, spawned_at=time.monotonic() - 100.0)


def test_catches_signal_reads_the_process_handlers():
    old = signal.signal(signal.SIGUSR2, lambda *_: None)
    try:
        assert catches_signal(os.getpid(), signal.SIGUSR2)
    finally:
        signal.signal(signal.SIGUSR2, old)
    assert not catches_signal(os.getpid(), signal.SIGUSR2)
    assert not catches_signal(2 ** 22 + 12345, signal.SIGUSR1)  # no such process


def test_an_actor_never_heard_from_is_named_once_with_its_stack_and_not_killed(tmp_path, caplog):
    la = Launcher(load_config(None, [f"runs_dir={tmp_path}", "actor.silent_restart_s=60"], environ={}))
    dumps, plain, heard, young = (_child(tmp_path, "actor-0", DUMPS), _child(tmp_path, "actor-1", PLAIN),
                                  _child(tmp_path, "actor-2", DUMPS), _child(tmp_path, "actor-3", DUMPS))
    young.spawned_at = time.monotonic()  # started a moment ago: not yet
    la.children = [dumps, plain, heard, young]
    la.progress.actor_seen["actor-2"] = time.monotonic()
    try:
        with caplog.at_level(logging.WARNING, logger="zenrl.launcher"):
            la._watch_silent()
            la._watch_silent()  # once per process
        told = [r.getMessage() for r in caplog.records if "has published nothing" in r.getMessage()]
        assert len(told) == 2 and told[0].startswith("actor-0 has published nothing in the 100 s since it started")
        assert f"its threads' stacks are in {dumps.log_path}" in told[0]
        assert told[1].startswith("actor-1 ") and f"its log: {plain.log_path}" in told[1]
        deadline = time.monotonic() + 10
        while "most recent call first" not in dumps.log_path.read_text() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert "most recent call first" in dumps.log_path.read_text()
        assert all(c.proc.poll() is None for c in la.children)  # nobody killed, the plain one not signalled
        assert "most recent call first" not in (tmp_path / "actor-2.log").read_text()
        # restarted (a new process): watched afresh
        dumps.spawned_at, dumps.unheard_told = time.monotonic() - 100.0, False
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="zenrl.launcher"):
            la._watch_silent()
        assert [r.getMessage()[:7] for r in caplog.records] == ["actor-0"]
    finally:
        for c in la.children:
            c.proc.kill()
            c.proc.wait()


class SlowToMake(gym.Env):
    observation_space = gym.spaces.Box(-1.0, 1.0, (2,))
    action_space = gym.spaces.Discrete(2)

    def __init__(self, wait_s: float = 0.0) -> None:
        time.sleep(wait_s)

    def reset(self, *, seed=None, options=None):
        return self.observation_space.sample(), {}


gym.register("SlowToMake-v0", entry_point=SlowToMake)


@pytest.mark.parametrize("wait_s, told", [(0.6, True), (0.0, False)])
def test_the_launchers_env_check_says_where_a_slow_env_waits(tmp_path, caplog, wait_s, told):
    cfg = load_config(None, [f"runs_dir={tmp_path}", f"env.id={__name__}:SlowToMake-v0",
                             f"env.kwargs={{wait_s: {wait_s}}}"], environ={})
    with caplog.at_level(logging.WARNING, logger="zenrl.launcher"):
        check_env(cfg, slow_s=0.2)
        time.sleep(0.3)  # past the watch's time: it must have stood down
    lines = [r.getMessage() for r in caplog.records if "once to check it has taken" in r.getMessage()]
    if told:
        assert len(lines) == 1 and "SlowToMake-v0 once to check it has taken 0 s (still waiting" in lines[0], lines
        assert "in __init__\n    time.sleep(wait_s)" in lines[0] and "check_env_now" in lines[0], lines[0]
    else:
        assert lines == []


def test_a_league_runs_other_agents_actors_are_watched_too(tmp_path, caplog):
    """The launcher's display shows the main agent's figures, but it hears every agent's actors
    (their stats on each agent's run id, through a real router session): an exploiter's actor
    that never published is named like the main agent's; one heard is not. Before, the other
    agents' actors were never heard and never watched."""
    from pathlib import Path

    from zenrl.common import protocol as P
    from zenrl.common.transport import Node, open_router
    from zenrl.launcher import free_port

    root = Path(__file__).resolve().parents[2]
    la = Launcher(load_config(root / "configs/burgerwar_league_pfsp.yaml", [f"runs_dir={tmp_path}", "run_id=lg1"],
                              environ={}))
    names = [c.name for c in la._plan() if c.role == "actor"]
    assert "main-actor-0" in names and "exploiter-actor-0" in names
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_router([ep])
    node, sender = Node(session=router), Node(ep, 10.0)
    kids = [_child(tmp_path, n, PLAIN) for n in ("main-actor-0", "exploiter-actor-0", "exploiter-actor-1")]
    for c in kids:
        c.agent = c.name.split("-")[0]
    la.children = kids
    try:
        la._listen(node)
        # exploiter-actor-1 reports on its agent's run id; the others say nothing
        ex = P.Keys(la.agents["exploiter"].run_id)
        stats = P.Stats("actor", "exploiter-actor-1", time.time(), {"env_steps": 5}).encode()
        deadline = time.monotonic() + 20
        while "exploiter-actor-1" not in la.progress.actor_seen and time.monotonic() < deadline:
            sender.put(ex.stats("actor", "exploiter-actor-1"), stats)
            time.sleep(0.05)
        assert "exploiter-actor-1" in la.progress.actor_seen
        assert la.progress.env_steps == 0  # heard alive, not counted in the main agent's figures
        with caplog.at_level(logging.WARNING, logger="zenrl.launcher"):
            la._watch_silent()
        told = sorted(r.getMessage().split()[0] for r in caplog.records)
        assert told == ["exploiter-actor-0", "main-actor-0"], told
    finally:
        for c in la.children:
            c.proc.kill()
            c.proc.wait()
        sender.close()
        node.close()
        router.close()


@pytest.mark.parametrize("interval_s, silent_s, killed", [(1, 100, True), (30, 80, False), (30, 95, True)])
def test_a_silent_evaluator_is_restarted_after_three_of_its_intervals_at_least(tmp_path, caplog, interval_s, silent_s,
                                                                                killed):
    la = Launcher(load_config(None, [f"runs_dir={tmp_path}", "actor.silent_restart_s=60",
                                     f"evaluator.interval_s={interval_s}"], environ={}))
    ev = _child(tmp_path, "evaluator", DUMPS)
    ev.role = "evaluator"
    la.children = [ev]
    la.progress.evaluator_seen = time.monotonic() - silent_s
    try:
        with caplog.at_level(logging.WARNING, logger="zenrl.launcher"):
            la._watch_silent()
        assert (ev.proc.poll() is not None) == killed
        if killed:
            assert ev.killed_for.startswith("killed by the launcher: no stats for") and la.progress.evaluator_seen is None
            assert "most recent call first" in ev.log_path.read_text()
        else:
            assert not caplog.records
    finally:
        if ev.proc.poll() is None:
            ev.proc.kill()
        ev.proc.wait()


def test_a_restarted_actor_is_judged_from_its_own_start(tmp_path, monkeypatch, caplog):
    """An actor restarted (after a crash, a league reset) is not heard yet: its predecessor's
    last stats must not count for it, or a slow start would be killed as stuck, restarted,
    killed again, until the run stopped on its restarts."""
    from zenrl.launcher import supervisor

    la = Launcher(load_config(None, [f"runs_dir={tmp_path}", "actor.silent_restart_s=60"], environ={}))
    (la.run_dir / "logs").mkdir(parents=True)
    real = subprocess.Popen
    monkeypatch.setattr(supervisor.subprocess, "Popen", lambda cmd, **kw: real([sys.executable, "-c", PLAIN], **kw))
    c = Child("actor-0", "actor", ["--id", "actor-0"])
    la.progress.actor_seen["actor-0"] = time.monotonic() - 50.0  # its predecessor's last stats
    la._spawn(c)
    la.children = [c]
    try:
        with caplog.at_level(logging.WARNING, logger="zenrl.launcher"):
            la._watch_silent(now=time.monotonic() + 20.0)  # 70 s after those stats, 20 s after its start
        assert c.proc.poll() is None and not caplog.records, [r.getMessage() for r in caplog.records]
    finally:
        c.proc.kill()
        c.proc.wait()
