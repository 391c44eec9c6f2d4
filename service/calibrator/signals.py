"""Ctrl-C and the calibrator's child processes: a terminal sends SIGINT to the whole process
group, the daemon (or replay) and its child alike. Only the parent acts on it (it stops the
child in order); the child ignores it, from the start of its interpreter, so no
KeyboardInterrupt traceback ever comes from it."""
from __future__ import annotations

import signal
import threading
from typing import Any


def ignore_sigint() -> None:
    """In a child: leave Ctrl-C to the parent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def start_ignoring_sigint(proc: Any) -> None:
    """``proc.start()`` with SIGINT ignored meanwhile (from the main thread), so the spawned
    interpreter inherits SIG_IGN and a Ctrl-C during its start-up cannot reach it either."""
    if threading.current_thread() is not threading.main_thread():
        proc.start()
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        proc.start()
    finally:
        signal.signal(signal.SIGINT, previous)
