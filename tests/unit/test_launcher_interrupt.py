"""Ctrl-C at the launcher (zenrl/launcher/supervisor.py): the first stops the run in order (each
child gets SIGTERM and its grace); a second, a moment later, kills what has not stopped yet; one
press delivered twice at once (``timeout -s INT`` signals the process and its group) is one."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

from zenrl.common.config import load_config
from zenrl.launcher.supervisor import HURRY_AFTER_S, Child, Launcher

STUBBORN = "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print('up', flush=True); time.sleep(120)"


def _stubborn_child() -> Child:
    p = subprocess.Popen([sys.executable, "-c", STUBBORN], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "up"  # its SIGTERM is ignored from here on
    return Child("actor-0", "actor", [], proc=p)


def _stop_in_thread(la: Launcher) -> threading.Thread:
    t = threading.Thread(target=la._terminate, kwargs={"grace_s": 60.0})
    t.start()
    return t


def test_a_second_ctrl_c_kills_what_has_not_stopped(tmp_path):
    la = Launcher(load_config(None, [f"runs_dir={tmp_path}"], environ={}))
    la.children = [_stubborn_child()]
    try:
        la._on_signal(signal.SIGINT)
        la._on_signal(signal.SIGINT)  # the same press, delivered twice: not a second one
        assert la.stop.is_set() and la.stop_reason == "interrupted by user (Ctrl-C)" and not la.hurry.is_set()
        t = _stop_in_thread(la)
        time.sleep(HURRY_AFTER_S + 0.2)
        assert t.is_alive()  # waiting out the child's grace (60 s)
        t0 = time.monotonic()
        la._on_signal(signal.SIGINT)  # the second press
        t.join(10)
        assert not t.is_alive() and time.monotonic() - t0 < 5
        assert la.children[0].proc.returncode == -signal.SIGKILL
    finally:
        for c in la.children:
            if c.proc.poll() is None:
                c.proc.kill()
                c.proc.wait()


def test_sigterm_after_ctrl_c_does_not_hurry(tmp_path):
    # a docker stop or kill after a Ctrl-C keeps the orderly stop (only a person presses twice)
    la = Launcher(load_config(None, [f"runs_dir={tmp_path}"], environ={}))
    la._on_signal(signal.SIGINT)
    time.sleep(HURRY_AFTER_S + 0.1)
    la._on_signal(signal.SIGTERM)
    assert not la.hurry.is_set() and la.stop_reason == "interrupted by user (Ctrl-C)"
