"""A new user's first contact with ``zenrl``, driven as they would drive it: a subprocess, its
exit code, what it prints and what it leaves on disk.

1. a mistake in the env fails at once with the env's reason, exit code 2 and no run folder; a
   child stopping on its configuration is not restarted and its error reaches the terminal;
2. ``zenrl status runs/<id>`` finds the run's router and shows rates and the evaluator, quietly;
3. ``summary.json`` says how a run ended and covers every segment of a resumed run."""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import ROOT, free_port, own_process_group, wait_until, zenrl_pids

pytestmark = pytest.mark.integration

CONFIG = "configs/cartpole_apex.yaml"
ZENOH_NOISE = re.compile(r"\bWARN\b|\.rs:\d+")
#: the bound on a command run beside a busy run (see test_status_ctrl_c_and_resume)
BUSY_TIMEOUT_S = 180


def zenrl(*args: str, timeout_s: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "zenrl.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout_s)


@contextlib.contextmanager
def launched(cmd: list[str]):
    """``cmd`` (a ``zenrl run``) started in a process group of its own, as from a terminal's
    shell (SIGHUP's default action: a test run under ``nohup`` would hand down its ignore), its
    output read at the end; killed if still running when the block ends."""
    hup = signal.signal(signal.SIGHUP, signal.SIG_DFL)  # inherited across exec, as ignored would be
    try:
        launcher = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                    **own_process_group())
    finally:
        signal.signal(signal.SIGHUP, hup)
    try:
        yield launcher
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()


def signal_group(launcher: subprocess.Popen, sig: int) -> str:
    """Send ``sig`` to the launcher's whole process group, as a terminal does; its output once it
    has exited."""
    os.killpg(launcher.pid, sig)
    return launcher.communicate(timeout=BUSY_TIMEOUT_S)[0]


def run_args(tmp_path, run_id: str, *sets: str) -> list[str]:
    cmd = ["run", "--config", CONFIG, "--run-id", run_id, "--set", f"runs_dir={tmp_path}",
           "--set", f"transport.listen=[tcp/127.0.0.1:{free_port()}]"]
    for s in sets:
        cmd += ["--set", s]
    return cmd


@pytest.mark.parametrize("sets, reason", [
    (("env.id=CartPol-v1",), "Did you mean: `CartPole`"),
    (("env.id=Pendulum-v1",), "algo: apex needs a Discrete action space"),
    (("algo=r2d2", "env.id=Pendulum-v1"), "algo: r2d2 needs a Discrete action space, got Box(-1.0, 1.0, (1,), float32); "
                                          "algo: impala (IMPALA / APPO) and a3c take continuous (Box) actions"),
    (("env.kwargs={gravity_typo: 1}",), "unexpected keyword argument 'gravity_typo'"),
    # a network whose weights no message can carry (the second, 40 GB, is never allocated)
    (("network.hidden=[4200,4200]",), "the apex network has 17,677,803 parameters (67.4 MiB), more than one "
                                      "weights message may carry (transport.max_message_bytes = 64.0 MiB)"),
    (("algo=impala", "network.hidden=[100000,100000]"), "the impala network has 10,000,"),
    (("learner.device=banana",), "learner.device = 'banana' is not a torch device: auto, cpu, cuda, cuda:N or mps"),
    (("env.id=tests.integration.custom_envs:IntWalk-v0", "env.kwargs={obs_size: 3}"),
     "zenrl: error: env tests.integration.custom_envs:IntWalk-v0 gave observation obs of shape (3,); its "
     "observation_space says (2,)"),
])
def test_env_mistake_fails_at_once_with_its_reason(tmp_path, run_id, sets, reason):
    p = zenrl(*run_args(tmp_path, run_id, *sets), timeout_s=60)
    assert p.returncode == 2, (p.returncode, p.stderr)
    errors = [x for x in p.stderr.splitlines() if x.startswith("zenrl: error:")]
    assert len(errors) == 1 and reason in errors[0], p.stderr
    assert "Traceback" not in p.stderr and "restarting" not in p.stderr
    assert not any(tmp_path.iterdir()), list(tmp_path.iterdir())  # no run folder, nothing started
    assert not zenrl_pids(run_id)


def test_child_config_error_is_not_restarted(tmp_path, run_id):
    """``--resume`` of a run that never saved a checkpoint: the learner refuses (exit 78); the
    launcher stops at once with the learner's reason instead of restarting it five times."""
    run_dir = tmp_path / run_id
    run_dir.mkdir()
    cfg = zenrl("config", "--config", CONFIG, "--run-id", run_id, "--set", f"runs_dir={tmp_path}",
                "--set", f"transport.listen=[tcp/127.0.0.1:{free_port()}]")
    assert cfg.returncode == 0, cfg.stderr
    (run_dir / "config.yaml").write_text(cfg.stdout)
    p = zenrl("run", "--resume", str(run_dir), "--no-progress", timeout_s=120)
    assert p.returncode == 2, (p.returncode, p.stderr[-3000:])
    assert "learner failed on its configuration" in p.stderr and "no checkpoint in" in p.stderr, p.stderr[-3000:]
    assert "restarting" not in p.stderr
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stop_reason"].startswith("learner failed on its configuration: ")
    assert summary["restarts"]["learner"] == 0
    assert (run_dir / "logs" / "learner.log").read_text().count("no checkpoint in") >= 1
    assert not zenrl_pids(run_id)

    missing = zenrl("run", "--resume", str(tmp_path / "no-such-run"))
    assert missing.returncode == 2 and "no such run folder" in missing.stderr, missing.stderr


def _status_json(run_dir) -> dict:
    p = zenrl("status", str(run_dir), "--json", "--wait", "4", timeout_s=60)
    assert p.returncode in (0, 1), p.stderr
    assert not ZENOH_NOISE.search(p.stderr), p.stderr
    return json.loads(p.stdout.strip().splitlines()[-1])


def _machine_share_sets() -> tuple[str, ...]:
    """Two replay shards, each a ring of 70% of the memory one replay may take (items of 55
    bytes): each fits the machine alone, the two together do not."""
    from zenrl.replay.store import SLOT_OVERHEAD_BYTES, machine_memory

    have = machine_memory()[0]
    return "replay.shards=2", f"replay.capacity={int(0.7 * have / (55 + SLOT_OVERHEAD_BYTES))}"


@pytest.mark.parametrize("case", ["one", "shards"])
def test_a_replay_larger_than_the_machine_stops_the_run_at_once(tmp_path, run_id, case):
    """replay.capacity of 10**11 transitions (terabytes once full): the replay, once the first
    chunk shows an item's size, stops on it before allocating (exit 2, not restarted) and the run
    stops with the line that names the setting; before, the ring was allocated lazily and
    the replay killed for memory hours later, or every chunk failed to allocate. ``shards``: two
    shards that each fit the machine alone but not together; `zenrl run` gives each half of it
    (before, each was checked against the whole machine, and the two filled it)."""
    sets = ("replay.capacity=100000000000",) if case == "one" else _machine_share_sets()
    p = zenrl(*run_args(tmp_path, run_id, *sets, "max_wall_s=240"), "--no-progress", timeout_s=300)
    assert p.returncode == 2, (p.returncode, p.stderr[-3000:])
    errors = [x for x in p.stderr.splitlines() if "stopped on a configuration error (not restarted)" in x]
    assert errors and "items of" in errors[0] and "GiB once full, and" in errors[0] \
        and "lower replay.capacity, or set replay.max_bytes" in errors[0], p.stderr[-3000:]
    if case == "one":
        assert "replay.capacity = 100,000,000,000 items of" in errors[0]
    else:
        assert "and 1/2 of the machine's memory (replay.replays_per_machine = 2) is" in errors[0] \
            or "and 1/2 of the container's memory limit" in errors[0], errors[0]
    summary = json.loads((tmp_path / run_id / "summary.json").read_text())
    name = "replay" if case == "one" else summary["stop_reason"].split()[0]
    assert name in ("replay", "replay-0", "replay-1"), summary["stop_reason"]
    assert summary["stop_reason"].startswith(f"{name} failed on its configuration: replay.capacity = ")
    assert summary["restarts"][name] == 0 and not zenrl_pids(run_id)


def test_status_ctrl_c_and_resume(tmp_path, run_id):
    run_dir = tmp_path / run_id
    # max_wall_s: a safety net only (the test stops the run with Ctrl-C), longer than every wait below
    cmd = [sys.executable, "-m", "zenrl.cli", *run_args(tmp_path, run_id, "target_return=null", "max_wall_s=900",
                                                          "evaluator.interval_s=1")]
    # a process group of its own (not a session: the kernel's autogroups would schedule the run
    # apart from the status commands below): Ctrl-C is sent to the whole group, as a terminal does
    with launched(cmd) as launcher:
        wait_until(lambda: (run_dir / "launcher.json").is_file(), 30, "launcher.json")

        def ready():
            rows = {r["role"]: r for r in _status_json(run_dir)["processes"]}
            ok = all(k in rows for k in ("replay", "learner", "actor", "evaluator")) \
                and rows["learner"].get("updates", 0) > 0 and rows["evaluator"].get("eval_return") is not None \
                and rows["actor"].get("rate") is not None
            return rows if ok else None

        rows = wait_until(ready, 60, "every role in zenrl status, the learner training")
        actor = rows["actor"]
        assert actor["rate_unit"] == "env steps/s" and 0 < actor["rate"] < actor["env_steps"], actor
        assert rows["learner"]["rate_unit"] == "updates/s" and rows["learner"]["rate"] > 0
        # commands beside a run at full speed on 2 cores take ~3 s; the timeouts are generous because
        # twice in CI one of them (or the test process itself) stood still for about a minute
        table = zenrl("status", str(run_dir), "--wait", "2", timeout_s=BUSY_TIMEOUT_S)
        assert table.returncode == 0 and not ZENOH_NOISE.search(table.stdout + table.stderr), table.stderr
        for role in ("replay", "learner", "actor", "evaluator"):
            assert role in table.stdout
        assert "env steps/s" in table.stdout and "return" in table.stdout, table.stdout
        # a second launcher on the same folder while it runs: refused at once, the run untouched
        for again in (["run", "--resume", str(run_dir), "--no-progress"], [*run_args(tmp_path, run_id), "--no-progress"]):
            p = zenrl(*again, timeout_s=BUSY_TIMEOUT_S)
            assert p.returncode == 2 and "is in use by another zenrl run (launcher pid" in p.stderr, p.stderr[-2000:]
        assert launcher.poll() is None and (run_dir / "launcher.json").is_file()
        # what Ctrl-C sends: SIGINT to every process of the group; the launcher forwards SIGTERM too,
        # so each child gets two signals at once (which once deadlocked a child's stop handler)
        out = signal_group(launcher, signal.SIGINT)
    assert launcher.returncode == 0, out[-3000:]
    assert "stopped: interrupted by user (Ctrl-C)" in out, out[-2000:]
    assert "did not stop within" not in out, out[-3000:]  # every child stopped by itself
    assert not ZENOH_NOISE.search(out), out[-2000:]
    first = json.loads((run_dir / "summary.json").read_text())
    assert first["stop_reason"] == "interrupted by user (Ctrl-C)"
    assert not (run_dir / "launcher.json").exists()
    ended = zenrl("status", str(run_dir))
    assert ended.returncode == 1 and "not running" in ended.stderr and "Ctrl-C" in ended.stderr, ended.stderr
    fresh = zenrl(*run_args(tmp_path, run_id), "--no-progress", timeout_s=60)  # the same id, not --resume
    assert fresh.returncode == 2 and "holds a run already" in fresh.stderr and "--resume" in fresh.stderr, fresh.stderr
    assert json.loads((run_dir / "summary.json").read_text()) == first  # untouched
    no_run = zenrl("status")
    assert no_run.returncode == 2 and "which run?" in no_run.stderr and "default" not in no_run.stdout

    # resume: the totals continue where the first segment stopped
    steps0 = first["env_steps"]
    p = zenrl("run", "--resume", str(run_dir), "--set", f"max_env_steps={steps0 + 5000}", "--set", "max_wall_s=120",
              timeout_s=180)
    assert p.returncode == 0, p.stderr[-3000:]
    progress = [json.loads(x.split("progress ", 1)[1]) for x in p.stderr.splitlines() if " progress {" in x]
    assert progress and progress[0]["env_steps"] >= steps0 and progress[0]["elapsed_s"] >= first["wall_s"], progress[:2]
    s = json.loads((run_dir / "summary.json").read_text())
    assert [seg["resumed"] for seg in s["segments"]] == [False, True]
    assert s["segments"][0]["env_steps"] == steps0 and s["segments"][0]["stop_reason"] == first["stop_reason"]
    assert s["env_steps"] == steps0 + s["segments"][1]["env_steps"] >= steps0 + 5000
    assert s["wall_s"] == pytest.approx(sum(seg["wall_s"] for seg in s["segments"]))
    assert s["stop_reason"].startswith(f"max_env_steps {steps0 + 5000} reached")
    assert len(s["evals"]) >= len(first["evals"]) and s["evals"][:len(first["evals"])] == first["evals"]
    assert not zenrl_pids(run_id)


def test_a_role_waiting_for_its_router_stops_at_once(tmp_path):
    """A mistyped --router (or a router that is down) keeps a role waiting up to
    transport.connect_timeout_s; Ctrl-C or SIGTERM meanwhile ends the wait at once, in one line."""
    dead = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    p = subprocess.Popen([sys.executable, "-m", "zenrl.cli", "replay", "--config", CONFIG, "--run-id", "nowhere",
                          "--router", dead, "--set", "transport.connect_timeout_s=60"], cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        def opening() -> bool:  # Zenoh's runtime threads exist: zenoh.open is waiting for the router
            try:
                names = [(t / "comm").read_text().strip() for t in Path(f"/proc/{p.pid}/task").iterdir()]
            except OSError:
                return False
            return "net-0" in names

        wait_until(lambda: opening() or p.poll() is not None, 60, "the replay to wait for its router")
        assert p.poll() is None, p.communicate()
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=30)
        took = time.monotonic() - t0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert took < 5, f"{took:.1f} s after SIGTERM"
    assert p.returncode == 2, (p.returncode, err[-2000:])
    assert err.strip().splitlines()[-1] == f"zenrl: error: stopped while waiting for the Zenoh router at {dead}", err[-2000:]


def test_a_terminal_that_hangs_up_stops_the_run_in_order(tmp_path, run_id):
    """SIGHUP to the run's process group, what a closing terminal (a lost SSH connection) sends:
    every process stops as on Ctrl-C, the learner's final checkpoint and the summary written, the
    run resumable; before, SIGHUP's default action killed them all where they stood."""
    run_dir = tmp_path / run_id
    cmd = [sys.executable, "-m", "zenrl.cli", *run_args(tmp_path, run_id, "target_return=null", "max_wall_s=600",
                                                          "learner.checkpoint_interval_s=2"),
           "--no-progress"]
    with launched(cmd) as launcher:
        wait_until(lambda: list((run_dir / "checkpoints").glob("ckpt-*.pt")) if (run_dir / "checkpoints").is_dir()
                   else None, BUSY_TIMEOUT_S, "the learner's first checkpoint")
        out = signal_group(launcher, signal.SIGHUP)
    assert launcher.returncode == 0, out[-3000:]
    assert "stopped: its terminal hung up (SIGHUP)" in out and "did not stop within" not in out, out[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stop_reason"] == "its terminal hung up (SIGHUP)" and not (run_dir / "launcher.json").exists()
    learner = (run_dir / "logs" / "learner.log").read_text()
    assert "signal SIGHUP received, stopping" in learner
    assert "checkpoint " in learner.split("signal SIGHUP received, stopping", 1)[1], learner[-2000:]  # the final one
    assert not zenrl_pids(run_id)
