"""The OS's name for a thread: what ``/proc/<pid>/task/<tid>/comm`` shows, and what ``hilsim up``'s
scheduling (:mod:`hilsim.launch.priorities`) goes by to leave a thread out of SCHED_FIFO (the recorder's
writing, the planner's planning). Python 3.11 names its threads for itself only. Reads and writes no key.
"""

from __future__ import annotations

import ctypes

PR_SET_NAME = 15


def name_os_thread(name: bytes) -> None:
    """Name the calling thread for the OS (at most 15 bytes kept); Linux only, else nothing."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_NAME, ctypes.c_char_p(name[:15]), 0, 0, 0)
    except (OSError, AttributeError):
        pass
