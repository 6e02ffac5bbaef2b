"""What the OS knows of our threads. A thread's name: what ``/proc/<pid>/task/<tid>/comm`` shows, and what
``hilsim up``'s scheduling (:mod:`hilsim.launch.priorities`) goes by to leave a thread out of SCHED_FIFO (the
recorder's writing, the planner's planning); Python 3.11 names its threads for itself only. And a child's
death signal, which the kernel ties to the thread that started it (PR_SET_PDEATHSIG): every child hilsim
starts (services, a run, the live viewer) asks for it here. Reads and writes no key.
"""

from __future__ import annotations

import ctypes
import signal

PR_SET_PDEATHSIG = 1
PR_SET_NAME = 15


def name_os_thread(name: bytes) -> None:
    """Name the calling thread for the OS (at most 15 bytes kept); Linux only, else nothing."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_NAME, ctypes.c_char_p(name[:15]), 0, 0, 0)
    except (OSError, AttributeError):
        pass


def sigterm_when_parent_dies() -> bool:
    """In a child (before exec): ask the kernel for SIGTERM when the thread that started it ends
    (PR_SET_PDEATHSIG); False where it cannot."""
    try:
        return ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM) == 0
    except OSError:
        return False
