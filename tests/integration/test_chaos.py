"""Chaos, bounded in time: during a real `zenrl run`, SIGKILL an actor, then the learner, then
the replay; the launcher restarts them (the learner resuming from its checkpoint, the replay from
its durable log). No process may hang, counters continue, the replay restores what was flushed,
weights keep flowing and learning continues."""

import json
import os
import re
import signal
import subprocess
import sys
import threading

import pytest

from zenrl.common import protocol as P
from zenrl.common.transport import Node
from tests.conftest import ROOT, free_port, wait_until, zenrl_pids

pytestmark = pytest.mark.integration


def _pids(run_id: str, role: str, ident: str | None = None) -> list[int]:
    return zenrl_pids(run_id, role, ident)


def _stop(launcher: subprocess.Popen) -> str:
    """SIGTERM the launcher as Ctrl-C would; its output. It must stop within 90 s."""
    launcher.send_signal(signal.SIGTERM)
    try:
        out, _ = launcher.communicate(timeout=90)
    except subprocess.TimeoutExpired:
        launcher.kill()
        raise AssertionError("the launcher hung on SIGTERM")
    return out


class Watch:
    """Latest stats per process and eval results, from the run's Zenoh keys."""

    def __init__(self, node: Node, keys: P.Keys) -> None:
        self.stats: dict[str, dict] = {}
        self.evals: list[tuple[int, float]] = []
        self.lock = threading.Lock()
        node.subscribe(keys.stats_all, self._on_stats)
        node.subscribe(keys.eval, self._on_eval)

    def _on_stats(self, key, payload):
        m = P.Stats.decode(payload)
        with self.lock:
            self.stats[f"{m.role}/{m.id}"] = m.values

    def _on_eval(self, key, payload):
        m = P.EvalResult.decode(payload)
        with self.lock:
            self.evals.append((m.version, float(m.returns.mean())))

    def get(self, name: str, field: str, default=0):
        with self.lock:
            return self.stats.get(name, {}).get(field, default)


def test_kill_actor_learner_replay_and_recover(tmp_path, run_id):
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    cmd = [sys.executable, "-m", "zenrl.cli", "run", "--config", "configs/cartpole_apex.yaml", "--run-id", run_id,
           "--no-progress", "--set", f"runs_dir={tmp_path}", "--set", f"transport.listen=[{ep}]",
           "--set", "max_wall_s=540", "--set", "target_return=null", "--set", "evaluator.interval_s=2",
           "--set", "learner.checkpoint_interval_s=2", "--set", "learner.log_interval_s=0.5",
           "--set", "replay.durable=true", "--set", "replay.stats_interval_s=0.5", "--set", "replay.snapshot_interval_s=2"]
    launcher = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    logs = tmp_path / run_id / "logs"
    try:
        with Node(ep, 60.0) as node:
            w = Watch(node, P.Keys(run_id))
            wait_until(lambda: w.get("learner/learner", "updates") >= 1500, 240, "1500 learner updates")
            wait_until(lambda: len(w.evals) >= 2, 60, "two evaluations")
            with w.lock:
                before = max(m for _, m in w.evals[-3:])

            # 1. an actor
            old = _pids(run_id, "actor", "actor-0")
            assert len(old) == 1
            steps = w.get("actor/actor-0", "env_steps")
            assert launcher.poll() is None
            os.kill(old[0], signal.SIGKILL)
            wait_until(lambda: (p := _pids(run_id, "actor", "actor-0")) and p != old, 60, "actor-0 restarted")
            wait_until(lambda: 0 < w.get("actor/actor-0", "env_steps") < steps, 60, "the new actor-0 stepping")

            # 2. the learner: it must resume from its checkpoint, counters and versions going on
            ckpt_updates = None
            old = _pids(run_id, "learner")
            version_before = w.get("learner/learner", "version")
            os.kill(old[0], signal.SIGKILL)
            wait_until(lambda: (p := _pids(run_id, "learner")) and p != old, 60, "learner restarted")
            m = wait_until(lambda: re.search(r"resumed from .*ckpt-(\d+)\.pt: (\d+) updates, weights version (\d+)",
                                             (logs / "learner.log").read_text()), 120, "the learner resuming")
            ckpt_updates, resumed_version = int(m.group(2)), int(m.group(3))
            assert ckpt_updates >= 1000
            assert resumed_version >= version_before   # never goes back
            wait_until(lambda: w.get("learner/learner", "version") > resumed_version, 60, "new weights after resume")

            # 3. the replay: restored from its log, at least what had been flushed
            durable = w.get("replay/replay", "durable_through")
            assert durable > 0
            old = _pids(run_id, "replay")
            os.kill(old[0], signal.SIGKILL)
            wait_until(lambda: (p := _pids(run_id, "replay")) and p != old, 60, "replay restarted")
            m = wait_until(lambda: re.search(r"replay restored (\d+) items \(keys up to (\d+)\)",
                                             (logs / "replay.log").read_text()), 120, "the replay restoring")
            restored_through = int(m.group(2)) + 1
            assert restored_through >= durable, (restored_through, durable)

            # weights keep flowing, learning continues
            v = w.get("learner/learner", "version")
            wait_until(lambda: w.get("learner/learner", "version") > v + 5, 120, "weights flowing after the kills")
            with w.lock:
                n_evals = len(w.evals)
            wait_until(lambda: len(w.evals) >= n_evals + 3, 120, "three evaluations after recovery")
            with w.lock:
                after = max(m for _, m in w.evals[n_evals:])
            assert after >= 0.5 * before, (before, after, w.evals)
            assert w.get("learner/learner", "updates") > ckpt_updates
    finally:
        out = _stop(launcher)
    assert launcher.returncode == 0, out[-3000:]
    summary = json.loads((tmp_path / run_id / "summary.json").read_text())
    assert summary["restarts"]["actor-0"] == 1 and summary["restarts"]["learner"] == 1 and summary["restarts"]["replay"] == 1
    assert not [p for role in ("actor", "learner", "replay", "evaluator") for p in _pids(run_id, role)]


def test_a3c_learner_killed_resumes_from_checkpoint(tmp_path, run_id):
    """A3C: SIGKILL the parameter server mid-run; the launcher restarts it from its checkpoint,
    the parameter version continues upward, and the workers' gradients are applied again."""
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    cmd = [sys.executable, "-m", "zenrl.cli", "run", "--config", "configs/cartpole_a3c.yaml", "--run-id", run_id,
           "--no-progress", "--set", f"runs_dir={tmp_path}", "--set", f"transport.listen=[{ep}]",
           "--set", "max_wall_s=300", "--set", "target_return=null", "--set", "evaluator.interval_s=2",
           "--set", "learner.checkpoint_interval_s=2", "--set", "learner.log_interval_s=0.5"]
    launcher = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    logs = tmp_path / run_id / "logs"
    try:
        with Node(ep, 60.0) as node:
            w = Watch(node, P.Keys(run_id))
            wait_until(lambda: w.get("learner/learner", "updates") >= 300, 180, "300 applied gradients")
            wait_until(lambda: "checkpoint " in (logs / "learner.log").read_text(), 60, "a checkpoint")
            old = _pids(run_id, "learner")
            assert len(old) == 1
            version_before = w.get("learner/learner", "version")
            os.kill(old[0], signal.SIGKILL)
            wait_until(lambda: (p := _pids(run_id, "learner")) and p != old, 60, "learner restarted")
            m = wait_until(lambda: re.search(r"resumed from .*ckpt-(\d+)\.pt: (\d+) updates, params version (\d+)",
                                             (logs / "learner.log").read_text()), 120, "the learner resuming")
            ckpt_updates, resumed_version = int(m.group(2)), int(m.group(3))
            assert ckpt_updates > 0
            assert resumed_version >= version_before   # never goes back
            wait_until(lambda: w.get("learner/learner", "updates") > ckpt_updates + 50, 120,
                       "workers' gradients applied after the restart")
            wait_until(lambda: any(v > resumed_version for v, _ in list(w.evals)), 120,
                       "an evaluation of post-restart parameters")
    finally:
        out = _stop(launcher)
    assert launcher.returncode == 0, out[-3000:]
    summary = json.loads((tmp_path / run_id / "summary.json").read_text())
    assert summary["restarts"]["learner"] == 1
    assert not [p for role in ("actor", "learner", "evaluator") for p in _pids(run_id, role)]
