"""Planner runs for a data set or an evaluation: every (query, planner, seed), each in a fresh process.

OMPL's random generator is process-wide and can be seeded only once, before anything samples; a
planner's draws then depend on everything created before it in that process. So that a run depends
on its own (query, planner, seed) only, each runs in a child forked from a parent that never touched
OMPL: the child seeds OMPL with the run's seed, plans with the iteration budget, times the path
(:mod:`hilsim.planning.trajectory`), measures the paper's ΣP and ΣA and returns one :class:`RunRecord`.
The same run in any order, on any number of workers, gives the same record; only ``cpu_s`` (the
planning time measured as the child's CPU time) varies. The planner choice's ``auto`` is such a run
too: its decision, then the planner it picked (and the next ones if that fails) with the run's seed.

:func:`run_all` keeps ``jobs`` children busy, shows progress on stderr and hands each record over as
it comes (the caller appends it to its CSV: a data set is resumable).
"""

from __future__ import annotations

import multiprocessing as mp
import multiprocessing.connection as mpc
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

from hilsim.planning.collision import ArmModel
from hilsim.planning.library import PlannerLibrary, reseed_ompl
from hilsim.planning.problem import Problem
from hilsim.planning.scoring import DEFAULT_CRITERION
from hilsim.planning.trajectory import TrajectoryError, acceleration_variance, joint_path_lengths, time_parameterize

WALL_CAP_S = 600.0  # a run stops on its iteration budget; this only ends a hung one


@dataclass(frozen=True)
class RunTask:
    scene: str
    query: int
    planner: str
    seed: int

    @property
    def key(self) -> tuple[str, int, str, int]:
        return self.scene, self.query, self.planner, self.seed


@dataclass
class RunRecord:
    scene: str
    query: int
    planner: str
    seed: int
    success: int  # 1 | 0
    sum_P: float  # Σ_i P_i of the timed trajectory [rad]; nan when it failed
    sum_A: float  # Σ_i A_i, the joints' acceleration variances
    duration_s: float  # of the timed trajectory
    waypoints: int
    iterations: int
    checks: int  # collision checks while planning (deterministic: the planning effort)
    used: str  # the planner that planned (auto: the one it picked, or the fallback that succeeded)
    message: str
    cpu_s: float  # planning time, CPU seconds of the run (measured: the one field that varies)
    decision_ms: float = 0.0  # auto: the choice's own time (features and model), measured

    @classmethod
    def columns(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    def row(self) -> dict[str, Any]:
        return asdict(self)


MEASURED = ("cpu_s", "decision_ms")  # the columns left out of a data set's hash
BROKEN = "error: "  # how the message of a run that broke (an exception, a crash) starts


class RunContext:
    """What every child needs, set up in the parent before forking (the children inherit it): the
    library, the budget, one collision model per scene, the queries."""

    def __init__(self, library: PlannerLibrary, models: dict[str, Any], queries: dict[str, list[tuple[Any, Any]]],
                 clearance: float, iterations: int | None = None, criterion: str = DEFAULT_CRITERION,
                 warm: Callable[[ArmModel], None] | None = None) -> None:
        # OMPL's modules imported here, once, not by every child (importing seeds nothing)
        import ompl.base
        import ompl.geometric
        import ompl.util  # noqa: F401

        self.library = library
        self.iterations = iterations or library.iterations
        self.clearance = clearance
        self.criterion = criterion
        self.queries = queries
        self.arms = {name: ArmModel(path, clearance) for name, path in models.items()}
        self.limits = {name: library.joint_limits(a.n, a.velocity_limits(), a.joint_names)
                       for name, a in self.arms.items()}
        if warm is not None:  # e.g. the planner choice's model and scene features, loaded once for all children
            for a in self.arms.values():
                warm(a)


def run_one(ctx: RunContext, task: RunTask) -> RunRecord:
    """One run in this process (a fresh child: OMPL is seeded here with the run's seed)."""
    from ompl import util as ou

    reseed_ompl(task.seed + 1)  # 0 is taken as 1: seeds 0 and 1 would be the same OMPL run
    ou.setLogLevel(ou.LOG_NONE)  # OMPL's own complaints ("zero-length path") would break the progress line
    arm = ctx.arms[task.scene]
    start, goal = ctx.queries[task.scene][task.query]
    planner = ctx.library.create(task.planner, criterion=ctx.criterion)
    arm.checks = 0
    pb = Problem(arm, np.asarray(start, float), np.asarray(goal, float), seed=task.seed,
                 max_iterations=ctx.iterations, time_limit=WALL_CAP_S, resolution=ctx.library.resolution)
    c0 = time.process_time()
    out = planner.solve(pb)
    cpu = time.process_time() - c0
    nan = float("nan")
    used = str(out.extra.get("planner", task.planner))
    decision_ms = float(out.extra.get("decision_s", 0.0)) * 1e3
    base = dict(scene=task.scene, query=task.query, planner=task.planner, seed=task.seed,
                iterations=out.iterations, checks=arm.checks, used=used, cpu_s=cpu, decision_ms=decision_ms)
    if out.path is None:
        return RunRecord(success=0, sum_P=nan, sum_A=nan, duration_s=nan, waypoints=0, message=out.message, **base)
    try:
        traj = time_parameterize(out.path, *ctx.limits[task.scene], dt=0.01)
    except TrajectoryError as e:
        return RunRecord(success=0, sum_P=nan, sum_A=nan, duration_s=nan, waypoints=len(out.path),
                         message=str(e), **base)
    return RunRecord(success=1, sum_P=float(np.sum(joint_path_lengths(traj.q))),
                     sum_A=float(np.sum(acceleration_variance(traj.qdd))), duration_s=traj.duration,
                     waypoints=len(out.path), message="ok", **base)


def _child(ctx: RunContext, task: RunTask, conn: mpc.Connection) -> None:
    try:
        conn.send(run_one(ctx, task))
    except Exception as e:  # a planner's error is this run's failure, said in its record
        conn.send(RunRecord(task.scene, task.query, task.planner, task.seed, 0, float("nan"), float("nan"),
                            float("nan"), 0, 0, 0, task.planner, f"{BROKEN}{type(e).__name__}: {e}", 0.0))
    finally:
        conn.close()


class Progress:
    """``what: k/N runs (p %), J workers, ETA`` on stderr: one line rewritten on a terminal, a line
    every 5 % elsewhere (a log file)."""

    def __init__(self, what: str, total: int, jobs: int) -> None:
        self.what, self.total, self.jobs = what, total, jobs
        self.done = 0
        self.t0 = time.monotonic()
        self.last = -1.0
        self.tty = sys.stderr.isatty()

    def step(self) -> None:
        self.done += 1
        now = time.monotonic()
        pct = 100.0 * self.done / max(self.total, 1)
        if self.tty and now - self.last < 0.5 and self.done < self.total:
            return
        if not self.tty and int(pct // 5) == int(self.last) and self.done < self.total:
            return
        left = (now - self.t0) / self.done * (self.total - self.done)
        line = (f"{self.what}: {self.done}/{self.total} runs ({pct:.0f} %), {self.jobs} workers, "
                f"{left / 60:.1f} min left")
        if self.tty:
            sys.stderr.write(f"\r{line}" + ("\n" if self.done == self.total else ""))
            self.last = now
        else:
            sys.stderr.write(line + "\n")
            self.last = pct // 5
        sys.stderr.flush()


def run_all(ctx: RunContext, tasks: Iterable[RunTask], jobs: int, on_record: Callable[[RunRecord], None],
            what: str = "runs") -> None:
    """Every task in a child of its own, ``jobs`` at a time; ``on_record`` gets each record as it comes
    (in completion order)."""
    todo = list(tasks)
    if not todo:
        return
    fork = mp.get_context("fork")
    progress = Progress(what, len(todo), jobs)
    running: dict[mpc.Connection, tuple[Any, RunTask]] = {}
    try:
        while todo or running:
            while todo and len(running) < max(1, jobs):
                task = todo.pop(0)
                recv, send = fork.Pipe(duplex=False)
                proc = fork.Process(target=_child, args=(ctx, task, send), daemon=True)
                proc.start()
                send.close()
                running[recv] = (proc, task)
            for conn in mpc.wait(list(running), timeout=1.0):
                proc, task = running.pop(conn)  # type: ignore[index]
                try:
                    rec = conn.recv()
                except EOFError:  # the child died without a word (a crash in native code)
                    proc.join()
                    rec = RunRecord(task.scene, task.query, task.planner, task.seed, 0, float("nan"), float("nan"),
                                    float("nan"), 0, 0, 0, task.planner, f"{BROKEN}worker died (exit {proc.exitcode})",
                                    0.0)
                conn.close()
                proc.join()
                on_record(rec)
                progress.step()
    finally:
        for conn, (proc, _) in running.items():
            proc.kill()
            proc.join()
            conn.close()
