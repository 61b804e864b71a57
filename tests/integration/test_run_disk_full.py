"""A disk that fills up under a whole `zenrl run` (its run folder on a real 4 MiB tmpfs): the
run goes on training, the terminal says the disk refuses writes, the learner checkpoints again
once there is room, and Ctrl-C stops it with its summary written and nothing left running.
Before: the launcher died on its summary.json with a traceback and then hung at exit (its Zenoh
session left open), and the learner's TensorBoard writer thread died and its next writes hung."""

import json
import os
import shutil
import signal
import subprocess
import sys

import pytest

from tests.conftest import ROOT, free_port, own_process_group, wait_until, zenrl_pids

pytestmark = pytest.mark.integration


def _status(run_dir) -> dict:
    p = subprocess.run([sys.executable, "-m", "zenrl.cli", "status", str(run_dir), "--json", "--wait", "3"], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    return {r["role"]: r for r in json.loads(p.stdout.strip().splitlines()[-1])["processes"]}


def _checkpoints(run_dir) -> list[str]:
    return sorted(p.name for p in (run_dir / "checkpoints").glob("ckpt-*.pt"))


def test_a_full_disk_under_a_run_stops_nothing(small_disk, tmp_path, run_id):
    run_dir = small_disk / run_id
    out_path = tmp_path / "terminal.txt"  # the terminal is not on the full disk
    cmd = [sys.executable, "-m", "zenrl.cli", "run", "--config", "configs/cartpole_apex.yaml", "--run-id", run_id,
           "--no-progress", "--set", f"runs_dir={small_disk}", "--set", f"transport.listen=[tcp/127.0.0.1:{free_port()}]",
           "--set", "target_return=null", "--set", "learner.checkpoint_interval_s=1", "--set", "max_wall_s=600"]
    with open(out_path, "w") as out:
        launcher = subprocess.Popen(cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, **own_process_group())
    try:
        wait_until(lambda: (run_dir / "checkpoints").is_dir() and _checkpoints(run_dir), 180, "a first checkpoint")
        with open(small_disk / "filler", "wb") as f:
            try:
                while True:
                    f.write(b"\0" * 65536)
                    f.flush()
            except OSError:
                pass
        assert shutil.disk_usage(small_disk).free < 65536
        wait_until(lambda: "No space left on device" in out_path.read_text(), 60, "the terminal saying the disk is full")
        full = _checkpoints(run_dir)
        first = _status(run_dir)["learner"]["updates"]
        wait_until(lambda: _status(run_dir)["learner"]["updates"] > first + 500, 120, "the learner training on a full disk")
        assert launcher.poll() is None, out_path.read_text()[-3000:]
        (small_disk / "filler").unlink()
        wait_until(lambda: _checkpoints(run_dir) and _checkpoints(run_dir)[-1] > full[-1], 60, "a checkpoint once there is room")
        os.killpg(launcher.pid, signal.SIGINT)
        launcher.wait(timeout=120)
    finally:
        if launcher.poll() is None:
            os.killpg(launcher.pid, signal.SIGKILL)
            launcher.wait()
    text = out_path.read_text()
    assert launcher.returncode == 0, text[-3000:]
    assert "Traceback" not in text and "did not stop within" not in text, text[-3000:]
    said = [x for x in text.splitlines() if "No space left on device" in x]
    assert said and all("going on" in x or "The run goes on" in x for x in said), said
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stop_reason"] == "interrupted by user (Ctrl-C)" and summary["learner"]["updates"] > first + 500
    assert not zenrl_pids(run_id), zenrl_pids(run_id)


def test_a_run_started_on_a_full_disk_says_so_in_one_line(small_disk, run_id):
    (small_disk / "filler").write_bytes(b"\0" * shutil.disk_usage(small_disk).free)
    p = subprocess.run([sys.executable, "-m", "zenrl.cli", "run", "--config", "configs/cartpole_apex.yaml", "--run-id",
                        run_id, "--set", f"runs_dir={small_disk}", "--set",
                        f"transport.listen=[tcp/127.0.0.1:{free_port()}]"], cwd=ROOT, capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 1, (p.returncode, p.stderr[-3000:])
    assert p.stderr.splitlines()[-1] == ("zenrl: error: [Errno 28] No space left on device (writing the run folder, "
                                         "its logs or checkpoints: see runs_dir)"), p.stderr[-3000:]
    assert "Traceback" not in p.stderr and not zenrl_pids(run_id)
