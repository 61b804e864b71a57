"""Stop signals (SIGTERM, SIGINT, SIGHUP) turned into a call on an ordinary thread.

A Python signal handler runs in the main thread, between two of its bytecodes, wherever that
thread is. A handler that sets a ``threading.Event`` takes the event's lock there, and the main
thread may already hold it: inside ``Event.wait`` or ``Event.set``, or inside the same handler
interrupted by a second signal. Two signals at once are the common case, not a corner: a terminal's
Ctrl-C and ``timeout`` signal the whole process group, and ``zenrl run`` forwards the signal to
its children as well, so each child gets it twice. The handler then waits forever on a lock its
own thread holds, and the process never stops (seen: a learner and an actor killed after the
launcher's 20 s grace).

So the Python-level handler here does nothing; the interpreter's C-level handler writes the
signal's number to a pipe (:func:`signal.set_wakeup_fd`, no Python lock involved), and a daemon
thread, ``signals``, reads it and makes the call. The main thread may keep running C code (a
torch step) meanwhile: the call still comes at once.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from typing import Any, Callable

log = logging.getLogger(__name__)

#: the signals that stop a zenrl process in order (its state saved, its session closed). SIGHUP:
#: a terminal that closes (an SSH connection lost) sends it to every process of its foreground
#: group, whose default action would kill them all where they stand
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
_STOP_NUMBERS = frozenset(int(s) for s in STOP_SIGNALS)


class _Relay:
    """The process's one wake-up pipe and the thread that reads it."""

    def __init__(self) -> None:
        self.callback: Callable[[int], None] | None = None
        r, w = os.pipe()  # not inherited by child processes (PEP 446)
        os.set_blocking(w, False)  # set_wakeup_fd requires it; a full pipe drops the byte, not the signal
        self.read_fd, self.write_fd = r, w
        self.thread = threading.Thread(target=self._run, name="signals", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            try:
                data = os.read(self.read_fd, 64)
            except InterruptedError:  # pragma: no cover - os.read retries EINTR itself (PEP 475)
                continue
            if not data:
                return
            for signum in data:
                cb = self.callback
                if signum not in _STOP_NUMBERS:  # another signal with a Python handler
                    continue
                stopping.set()
                if cb is None:
                    continue
                try:
                    cb(signum)
                except Exception:  # noqa: BLE001 - a failing callback must not end the relay
                    log.exception("handling signal %d failed", signum)


#: set once this process got a stop signal: a wait at start-up (for the router) gives up on it
stopping = threading.Event()

_relay: _Relay | None = None
_relay_lock = threading.Lock()


def _noted(_signum: int, _frame: Any) -> None:
    """The Python-level handler: nothing (the relay thread acts); installed so that the signal
    does not take its default action and the C-level handler writes the wake-up byte."""


def on_stop_signals(callback: Callable[[int], None]) -> None:
    """Call ``callback(signum)`` on the ``signals`` thread for each stop signal, instead
    of the signal's default action (a later call replaces the callback). Call from the main
    thread (Python's rule for signal handlers). The callback may take locks and set events; it
    runs while the main thread goes on."""
    global _relay
    with _relay_lock:
        if _relay is None:
            _relay = _Relay()
        _relay.callback = callback
        old = signal.set_wakeup_fd(_relay.write_fd, warn_on_full_buffer=False)
        if old not in (-1, _relay.write_fd):
            log.warning("signal wake-up fd %d replaced by zenrl's stop-signal relay", old)
    for s in STOP_SIGNALS:
        if s == signal.SIGHUP and signal.getsignal(s) == signal.SIG_IGN:
            continue  # `nohup zenrl run ...`: asked to outlive its terminal (children inherit the ignore)
        signal.signal(s, _noted)


def install_stop_signals(stop: threading.Event) -> None:
    """The stop signals set ``stop`` (so the process closes its session and saves state)
    instead of killing the interpreter. Call from the main thread."""

    def on_signal(signum: int) -> None:
        log.info("signal %s received, stopping", signal.Signals(signum).name)
        stop.set()

    on_stop_signals(on_signal)
