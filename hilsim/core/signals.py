"""Signals delivered where taking locks is safe: a watcher thread, not a Python signal handler.

Used by every service and by ``hilsim up``, ``hilsim router`` and ``hilsim play`` for Ctrl-C and SIGTERM.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable


def watch_signals(on_signal: Callable[[int], None],
                  signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> Callable[[], None]:
    """Call ``on_signal(signum)`` from a watcher thread for every one of ``signals`` that arrives (main
    thread only; elsewhere nothing is installed); returns what puts the previous handlers back.

    A Python signal handler runs in the main thread between two bytecodes, maybe while that
    thread holds a lock: inside ``Event.wait``, or in a first handler's ``Event.set`` when a
    second signal lands. Setting an Event there took its non-reentrant lock twice and hung the
    process for good (seen: a controller that outlived its killed launcher); one that raised
    (KeyboardInterrupt) cut the launcher's own stopping short. So the handlers do nothing (set
    explicitly: a process started in the background of a script inherits SIGINT ignored); the
    interpreter's C handler writes the signal number to a wake-up pipe, and a thread reads it and
    calls back where taking locks is safe."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None  # signals reach the main thread only: its caller's business
    r, w = os.pipe()
    os.set_blocking(w, False)
    old_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
    old = {s: signal.signal(s, lambda *_: None) for s in signals}
    wanted = {int(s) for s in signals}

    def watch() -> None:
        while True:
            try:
                data = os.read(r, 64)
            except OSError:
                return
            if not data:
                return
            for b in data:
                if b in wanted:
                    on_signal(b)

    t = threading.Thread(target=watch, daemon=True, name="signals")
    t.start()

    def restore() -> None:
        signal.set_wakeup_fd(old_fd)
        for s, h in old.items():
            signal.signal(s, h)
        os.close(w)  # the watcher reads the end of the pipe and returns
        t.join(1.0)
        os.close(r)

    return restore


def on_stop_signals(callback: Callable[[], None], signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> None:
    """Call ``callback`` (from a watcher thread, :func:`watch_signals`) when one of ``signals`` arrives."""
    watch_signals(lambda _signum: callback(), signals)
