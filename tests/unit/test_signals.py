"""Stop signals (common/signals.py): a signal that lands while the main thread holds the stop
event's lock still stops the process. Each case runs in a child interpreter of its own (signal
handlers are per process, and pytest's Ctrl-C must stay pytest's)."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def run_child(code: str, timeout_s: float = 20.0) -> subprocess.CompletedProcess:
    try:
        return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, capture_output=True,
                              text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired as e:  # the deadlock this module is about: name it
        raise AssertionError(f"the child did not stop within {timeout_s} s (deadlocked?); "
                             f"stdout {e.stdout!r}, stderr {e.stderr!r}") from None


def test_a_signal_inside_the_events_lock_still_stops() -> None:
    # The main thread holds the stop event's lock (as inside Event.wait or Event.set, or a first
    # handler interrupted by a second signal) when the handler runs: a handler that set the
    # event itself would wait on that lock forever.
    r = run_child("""
        import os, signal, threading
        from zenrl.common.signals import install_stop_signals

        stop = threading.Event()
        install_stop_signals(stop)
        with stop._cond:  # threading.Event's own lock
            os.kill(os.getpid(), signal.SIGTERM)
            n = 0
            for i in range(100_000):  # bytecodes: the Python-level handler runs in here
                n += i
            print("handler returned while the lock was held", flush=True)
        print("stopped" if stop.wait(10) else "not stopped", flush=True)
    """)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[-1:] == ["stopped"], r.stdout
    assert "handler returned while the lock was held" in r.stdout


def test_two_signals_at_once_and_only_stop_signals_count() -> None:
    # SIGINT and SIGTERM together (a terminal's Ctrl-C to the process group plus the launcher's
    # forwarded SIGTERM); a SIGUSR1 with a Python handler of its own also wakes the relay and must
    # be ignored by it. The pipe keeps their order, so the callback sees exactly the stop signals.
    r = run_child("""
        import os, signal, threading
        from zenrl.common.signals import on_stop_signals

        seen, done = [], threading.Event()
        def on_signal(signum):
            seen.append(signal.Signals(signum).name)
            if len(seen) == 2:
                done.set()
        on_stop_signals(on_signal)
        signal.signal(signal.SIGUSR1, lambda *_: None)
        os.kill(os.getpid(), signal.SIGUSR1)
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGTERM)
        print("done" if done.wait(10) else "timeout", sorted(seen), flush=True)
    """)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "done ['SIGINT', 'SIGTERM']", r.stdout


def test_the_default_action_is_replaced() -> None:
    # without a handler SIGTERM would end the interpreter at once (exit -15): the process goes on
    # to its own orderly end
    r = run_child("""
        import os, signal, threading
        from zenrl.common.signals import install_stop_signals

        stop = threading.Event()
        install_stop_signals(stop)
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGINT)
        print("stopped" if stop.wait(10) else "not stopped", flush=True)
    """)
    assert r.returncode == 0, (r.returncode, r.stderr)
    assert r.stdout.strip() == "stopped"


HANGUP = """
    import os, signal, threading
    from zenrl.common.signals import install_stop_signals
    stop = threading.Event()
    install_stop_signals(stop)
    os.kill(os.getpid(), signal.SIGHUP)
    print("stopped" if stop.wait(2.0) else "running", flush=True)
"""


@pytest.mark.parametrize("inherited, after", [(signal.SIG_DFL, "stopped"), (signal.SIG_IGN, "running")])
def test_a_hangup_stops_in_order_unless_the_process_was_started_to_ignore_it(inherited, after) -> None:
    """SIG_IGN: started under ``nohup`` (the ignore is set before exec and kept across it); the
    default is set explicitly, as this test itself may run under ``nohup``."""
    before = signal.signal(signal.SIGHUP, inherited)  # what the child inherits across exec
    try:
        p = subprocess.run([sys.executable, "-c", textwrap.dedent(HANGUP)], cwd=ROOT, capture_output=True, text=True,
                           timeout=20)
    finally:
        signal.signal(signal.SIGHUP, before)
    assert p.returncode == 0 and p.stdout.strip() == after, (p.stdout, p.stderr)
