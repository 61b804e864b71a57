"""The run-folder lock (zenrl/launcher/runfolder.py): one launcher per folder, and no stale lock
after its holder dies however it dies."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest

from tests.conftest import ROOT
from zenrl.common.errors import ConfigError
from zenrl.launcher.runfolder import LAUNCHER_FILE, holds_a_run, lock_run_folder, unlock_run_folder

HOLD = """
import sys, time
from pathlib import Path
from zenrl.launcher.runfolder import lock_run_folder
lock_run_folder(Path(sys.argv[1]))
print("locked", flush=True)
time.sleep(600)
"""


def test_a_second_holder_is_refused_until_the_first_dies(tmp_path):
    run_dir = tmp_path / "r1"
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(run_dir)], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        (run_dir / LAUNCHER_FILE).write_text(json.dumps({"router": "tcp/127.0.0.1:1", "pid": holder.pid}))
        with pytest.raises(ConfigError, match=rf"is in use by another zenrl run \(launcher pid {holder.pid}\)"):
            lock_run_folder(run_dir)
        holder.send_signal(signal.SIGKILL)  # no chance to let go: the OS does
        holder.wait(10)
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait()
    fd = lock_run_folder(run_dir)
    try:
        with pytest.raises(ConfigError, match="in use by another zenrl run"):  # this process's own, once more
            lock_run_folder(run_dir)
    finally:
        unlock_run_folder(fd)
    unlock_run_folder(lock_run_folder(run_dir))  # let go: free again


def test_a_folder_holds_a_run_once_it_has_its_config(tmp_path):
    assert not holds_a_run(tmp_path / "none")
    unlock_run_folder(lock_run_folder(tmp_path / "r2"))  # the lock alone makes no run
    assert not holds_a_run(tmp_path / "r2") and os.path.isdir(tmp_path / "r2")
    (tmp_path / "r2" / "config.yaml").write_text("algo: apex\n")
    assert holds_a_run(tmp_path / "r2")


def test_a_runs_dir_that_cannot_hold_folders_is_named(tmp_path):
    f = tmp_path / "a-file"
    f.write_text("")
    with pytest.raises(ConfigError, match=rf"cannot use the run folder .* \(runs_dir '{f}'\): Not a directory"):
        lock_run_folder(f / "run1")
