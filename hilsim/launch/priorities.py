"""The scheduling of a run's processes: who runs on SCHED_FIFO at which priority, who is niced.

The launcher's own process (the run's router) asks for SCHED_FIFO below physics in a realtime run
(:func:`raise_router_priority`); each service, once it has announced itself, gets its class here
(:func:`prioritise_ready`): realtime, the loop's services on SCHED_FIFO (the planner or navigator
lowest, the planner's planning thread ordinary and niced up) and the recorder's receiving too, its
writing threads left ordinary; lockstep, the recorder niced. The children start in an ordinary class
whatever the launcher's (:mod:`hilsim.launch.processes`).
Reads and writes no key.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

LOGGER_NICE = 10
ROUTER_PRIORITY = 5  # realtime: SCHED_FIFO of the run's router (physics 10, the HIL bridges 20)
LOOP_PRIORITY = 8  # realtime: SCHED_FIFO the launcher gives the loop's services that asked for none
PLANNING_PRIORITY = 1  # …and the planner or navigator: below every other, its plans are bursts of CPU
# realtime: the planner's planning thread stays in the ordinary class, niced up: on SCHED_FIFO its plans
# (a second of CPU) held one core of two while physics spun on the other, and every ordinary thread, the
# recorder's worker with the GIL among them, waited them out: the recorder heard nothing for ~1 s (issue 42)
PLANNING_THREADS = ("planner-worker",)
PLANNING_NICE = -10
LOGGER_PRIORITY = 1  # realtime: the recorder's receiving (its worker stays in the ordinary class)
# the recorder's writing threads (its worker, Rerun's), left in the ordinary class, niced up: beside four
# busy loops at nice 0 its worker shared what the loop left equally with them (a CAN demo lost 80 %)
RERUN_THREADS = ("logger-worker", "ChunkBatcher", "RecordingStream", "file_writer", "jemalloc")
WRITING_NICE = -10


def realtime_process(pid: int, priority: int, skip: tuple[str, ...] = ()) -> bool:
    """Give every thread of a process that has an ordinary scheduling class SCHED_FIFO ``priority``
    (threads it makes later inherit it; one that asked for its own class keeps it), but those whose name
    starts with one of ``skip``. False: not permitted (root or CAP_SYS_NICE) or gone."""
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return False
    for tid in tids:
        try:
            if skip and Path(f"/proc/{pid}/task/{tid}/comm").read_text().startswith(skip):
                continue
            if os.sched_getscheduler(int(tid)) == os.SCHED_OTHER:
                os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(priority))
        except (ProcessLookupError, FileNotFoundError):
            continue  # a thread that ended since the listing: the others still get the class (as renice)
        except OSError:
            return False
    return True


def renice(pid: int, nice: int, only: tuple[str, ...] = ()) -> None:
    """Give every thread of a process (or only those whose name starts with one of ``only``) the niceness
    ``nice`` (Linux keeps it per thread; threads made later inherit their maker's). A thread that ends
    meanwhile is passed over, and the threads are listed again until a pass finds none left to set (one made
    during a pass by a thread not yet set keeps its maker's: a CI run's recorder kept a thread at nice 0,
    the rest of a pass given up on a thread gone). Gone or not permitted: left as it is."""
    for _ in range(5):
        try:
            tids = os.listdir(f"/proc/{pid}/task")
        except OSError:
            return  # the process is gone
        changed = False
        for tid in tids:
            try:
                if only and not Path(f"/proc/{pid}/task/{tid}/comm").read_text().startswith(only):
                    continue
                if os.getpriority(os.PRIO_PROCESS, int(tid)) != nice:
                    os.setpriority(os.PRIO_PROCESS, int(tid), nice)
                    changed = True
            except (ProcessLookupError, FileNotFoundError):
                continue  # ended since the listing
            except OSError:
                return  # not permitted: as it is
        if not changed:
            return


def raise_router_priority(say: Callable[[str], None]) -> None:
    """Realtime: every sample of the loop crosses the run's router, in this process. Physics steps
    with SCHED_FIFO, and so do the HIL bridges (config/hil/can.yaml), but on a machine busy with
    other work the router's threads waited for a CPU for a quarter of a second at a time, and
    physics faulted a joint server as silent whose estimates were on their way (issue 36). So the
    router gets SCHED_FIFO too, below physics, and so do the threads Zenoh starts later (its receive
    and send runtimes start with their first link: with SCHED_RESET_ON_FORK they came up ordinary);
    the processes this one starts are set back to an ordinary class
    (:func:`hilsim.launch.processes.pdeathsig`). Without the privilege (root or CAP_SYS_NICE) it stays as
    it is."""
    try:
        for tid in sorted(int(t) for t in os.listdir("/proc/self/task")):
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(ROUTER_PRIORITY))
    except (PermissionError, AttributeError, OSError) as e:
        say(f"  (the router could not get a real-time scheduling class: {e}; on a busy machine the "
            "realtime loop's samples may wait for it)")


def prioritise_ready(name: str, pid: int, realtime: bool, own_router: bool) -> None:
    """The scheduling of launch unit ``name`` (process ``pid``) once every service of it has announced
    itself; ``own_router``: the run's router is this process's, on SCHED_FIFO."""
    if realtime and name != "logger" and own_router:
        # realtime, with the run's own router on SCHED_FIFO: the loop's services too, once set
        # up (physics and the HIL bridges ask for more themselves), so that other work on the
        # machine cannot hold a step; the planner or navigator lowest (its plans are bursts)
        units = name.split("+")
        planning = {"planner", "navigator"}.intersection(u.split("@")[0] for u in units)
        realtime_process(pid, PLANNING_PRIORITY if planning and len(units) == 1 else LOOP_PRIORITY,
                         skip=PLANNING_THREADS)
        renice(pid, PLANNING_NICE, only=PLANNING_THREADS)
    if name == "logger" and realtime:
        # Realtime: the recorder's receiving on SCHED_FIFO like the loop's services (lowest), so that
        # no other work on the machine makes it drop samples; its worker (writing the files, the
        # bulk of its CPU) puts itself back to the ordinary class (services/logger.py), niced up (not
        # down: at nice 10 two runs' recorders each lost a quarter of their samples) so that other work
        # on the machine gets less than it; its queue is bounded, what it cannot write in time is lost.
        if own_router:
            realtime_process(pid, LOGGER_PRIORITY, skip=RERUN_THREADS)
            renice(pid, WRITING_NICE, only=RERUN_THREADS)
    elif name == "logger":
        # Lockstep: the recorder runs at a lower CPU priority once it is set up: it buffers what it
        # receives, so on a small machine the loop's services get the cores first and it
        # catches up when idle. Not before: niced from its start, on a machine busy with
        # other work it took minutes to import and set up, and the whole run (and a HIL
        # device's start-up timeouts) waited for it.
        renice(pid, LOGGER_NICE)
