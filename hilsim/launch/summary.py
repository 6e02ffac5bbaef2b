"""``hilsim up``'s summary: what the run came to, printed at its end, and its exit code.

:func:`summarise` judges the :class:`~hilsim.launch.follow.Outcome` the launcher followed (the task's
result per robot, the final errors, dead or restarted services, a stalled lockstep, faults) and, where
this host ran the recorder, the recording: the counts the logger wrote to
``<run dir>/record_summary.json`` (received, recorded, lost, dropped per key) against what every service
says it published (``published:<key>`` in its final health), and the bag (``<run dir>/bag/``): the
messages per key counted in its files against what the recorder received; a recorder that died has its
``recording.rrd`` parts recovered (:mod:`hilsim.core.recording`) and its bag made whole
(:func:`hilsim.record.bag_read.recover_bag`). The result and the exit code of ``hilsim up``:

- ``OK`` (0): every target reached (or a run without a task ended as planned), nothing failed;
- ``FAILED`` (1): a target missed, a fault reported, a service died or never announced itself, the
  lockstep stalled, or the recording is not whole (lockstep: anything lost, an expected latched topic
  missing; realtime: more of the samples missed than ``logger.max_loss``, ``FAILED (recording lost N %)``);
- ``STOPPED (duration) 1/3 targets`` (3): ``--duration`` ended the run before its task, and
  nothing failed until then;
- ``INTERRUPTED (SIGINT) 1/3 targets`` (128 + the signal: 130, SIGTERM 143): a stop signal ended
  the run before its task. A run without a task (no targets and no duration, ``--interactive``)
  is meant to end so: it is judged as usual, unless its services had to be killed (a second signal).

(2 is a configuration error, said before anything starts: :mod:`hilsim.cli`.)

Reads and writes no Zenoh key: only the outcome and the run directory.
"""

from __future__ import annotations

import signal
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

from hilsim.core.config import Scenario
from hilsim.core.keys import UnknownKey, topic_name
from hilsim.core.recording import read_counts, recording_parts
from hilsim.launch.follow import Outcome

EXIT_OK, EXIT_FAILED, EXIT_STOPPED = 0, 1, 3  # and 128 + N: interrupted by signal N (SIGINT: 130)
TASK_HOSTS = {"planner", "navigator"}  # the services that run a scenario's task.targets (hilsim.sim.tasks)


class FinishedRun(Protocol):
    """What the summary reads of a run (a :class:`hilsim.launch.launcher.Launcher` once stopped)."""

    @property
    def sc(self) -> Scenario: ...
    @property
    def outcome(self) -> Outcome: ...
    @property
    def robots(self) -> list[str]: ...
    @property
    def local(self) -> list[str]: ...  # the launch units started on this host
    @property
    def run_dir(self) -> Path: ...
    @property
    def untrusted(self) -> int: ...  # samples ignored: not from the services


def summarise(la: FinishedRun) -> int:
    """Print the summary of a stopped run; its exit code (see the module's docstring): 0
    (``result: OK``), 1 (``FAILED``), 3 (``STOPPED (duration)``) or 128 + the signal (``INTERRUPTED``)."""
    o, sc = la.outcome, la.sc
    # the task's targets, if a service runs them (the planner; the rover's navigator)
    n_targets = len(sc.task.targets) if TASK_HOSTS.intersection(sc.services) else 0
    # with no task and no duration, Ctrl-C is how a run ends (--interactive): not an interruption
    open_ended = not n_targets and sc.duration is None
    interrupted = o.interrupted and (not open_ended or bool(o.killed))
    # a fault is a failure, whether or not the run went on (it may have run out its duration)
    ok = not o.died and not o.stalled and not o.faults and not o.not_started
    # a task goal that failed: a missed target, even if the run was cut short afterwards
    ok = ok and not any(not r.success and r.goal_id.startswith("task-") for r in o.results)
    unfinished = False  # a task without its result: cut short (duration, signal) or a failure
    reached_all, n_all = 0, n_targets * len(la.robots)
    print("summary:")
    if n_targets and len(la.robots) > 1:  # robots > 1: each robot's own task
        for robot in la.robots:
            reached = sum(1 for r, who in zip(o.results, o.result_robots, strict=True)
                          if who == robot and r.success and r.goal_id.startswith("task-"))
            reached_all += reached
            task = o.tasks.get(robot)
            if task is None:
                print(f"  {robot}: targets reached {reached}/{n_targets}, task not finished")
                unfinished = True
                continue
            err = max((abs(e) for e in task.execution_error), default=float("nan"))
            print(f"  {robot}: targets reached {reached}/{n_targets}, final max joint error {err:.4f} rad")
            ok = ok and task.success and reached == n_targets
    elif n_targets:
        reached = reached_all = sum(1 for r in o.results if r.success and r.goal_id.startswith("task-"))
        print(f"  targets reached: {reached}/{n_targets}")
        if o.task is not None:
            # the joints as the planner named them in its trajectories (index if it sent none)
            named = next((list(r.trajectory.joint_names) for r in o.results if r.trajectory.joint_names), [])
            err = o.task.execution_error
            names = named if len(named) == len(err) else [f"#{i}" for i in range(len(err))]
            errs = ", ".join(f"{n} {e:+.4f}" for n, e in zip(names, err, strict=True))
            if "navigator" in sc.services and len(err) == 2:  # the rover: [position m, yaw rad]
                print(f"  final error: position {err[0]:.3f} m, yaw {err[1]:.3f} rad (odometry)")
            else:
                print(f"  final error per joint [rad]: {errs}")
            ok = ok and o.task.success and reached == n_targets
        else:
            print("  task: not finished")
            unfinished = True
    ph = o.health.get("physics", {})
    if ph:
        print(f"  sim time {ph.get('sim_time', '?')} s, real-time factor {ph.get('real_time_factor', '?')}, "
              f"clock {sc.clock.mode}, seed {sc.seed}")
    for name, h in sorted(o.health.items()):
        bad = _num(h.get("rejected")) + _num(h.get("errors"))
        if bad:
            last = f" (last: {h['last_error']})" if h.get("last_error") else ""  # none: no empty "(last: )"
            print(f"  {name}: {h.get('rejected')} rejected, {h.get('errors')} errors{last}")
        if h.get("last_refused"):  # a command the controller did not take, and why (use_sim_time, ended, …)
            print(f"  {name}: {h.get('trajectories_refused')} trajectories refused (last: {h['last_refused']})")
        if _num(h.get("suspect")):
            print(f"  {name}: {h['suspect']} suspect samples (a writer's id in samples out of its order: delivered, "
                  "its gaps not counted as lost; docs/keys.md)")
    rrd = la.run_dir / "recording.rrd"
    lost_share: float | None = None  # realtime: the share of the samples the recording missed, past logger.max_loss
    if any("logger" in u.split("+") for u in la.local):  # a recorder on another host summarises there
        # a recorder that died left no footer (and no counts): make its file whole, say what it holds
        logger_restarted = any(r.name == "logger" for r in o.restarts)
        if logger_restarted or any(n == "logger" for n, _ in o.died) or "logger" in o.killed:
            ok = _recover_recordings(la.run_dir) and ok
        summary = la.run_dir / "record_summary.json"
        if summary.exists():
            counts, stopped = read_counts(summary)
            rec = sum(v.get("recorded", 0) for v in counts.values())
            recv = sum(v.get("received", 0) for v in counts.values())
            mismatch = sorted(k for k, v in counts.items() if v.get("received") != v.get("recorded"))
            lost = {k: v["lost"] for k, v in counts.items() if v.get("lost")}
            # one count per cause: dropped by the recorder (a part of lost), the rest lost in transport
            n_lost = sum(lost.values())
            n_full = sum(min(v.get("dropped", 0), v.get("lost", 0)) for v in counts.values())
            realtime = sc.clock.mode == "realtime"

            def short(key: str) -> str:  # keys as the user names them: clock, truth/joint_states, …
                try:
                    name = topic_name(key)
                except UnknownKey:
                    return key
                own = f"/{sc.robot}/"
                return name[len(own):] if name.startswith(own) else name.lstrip("/")

            line = f"  recorded {rec} of {recv} received messages on {len(counts)} keys"
            suspect = {k: v["suspect"] for k, v in counts.items() if v.get("suspect")}
            contested = sum(v.get("contested", 0) for v in counts.values())
            if n_lost:
                where = "in transport"
                if n_full:
                    where = f"({n_lost - n_full} in transport, {n_full} dropped by the recorder)"
                why = "realtime: the recorder could not keep up" if realtime else "lockstep, where nothing may be lost"
                top = sorted(lost.items(), key=lambda kv: (-kv[1], kv[0]))
                keys = ", ".join(f"{short(k)} {n}" for k, n in top[:8]) + (", …" if len(top) > 8 else "")
                line += f"; lost {n_lost} {where} ({why}): {keys}"
            if mismatch:
                line += f"; MISMATCH (received but not recorded) on {mismatch}"
            print(line)
            # the latched keys the run publishes once (/tf_static, robot_description): a viewer cannot draw without
            missing = sorted(short(k) for k, v in counts.items() if v.get("expected") and not v.get("recorded"))
            if missing:
                print(f"  expected but never recorded: {', '.join(missing)} (latched, put once at its writer's start"
                      + (")" if realtime else "; lockstep promises every sample)"))
            # batches: a writer outside them (a ROS 2 node) is subscribed once its publisher token is seen; what
            # it put before that subscription reached it is not in the recording (said, not a failure)
            early = {k: v.get("before_first", 0) for k, v in counts.items() if v.get("key_subscribed")}
            early = {k: n for k, n in early.items() if n}
            if early:
                keys = ", ".join(f"{short(k)} {n}" for k, n in sorted(early.items(), key=lambda kv: -kv[1])[:8])
                print(f"  not recorded: {sum(early.values())} samples their writers published before the recorder "
                      f"subscribed to them (logger.batch: docs/recording.md, \"Batches\"): {keys}")
            # a service's batch holding a key the key table does not let it write (a forged or foreign sample)
            refused = {k: v["batch_refused"] for k, v in counts.items() if v.get("batch_refused")}
            if refused:
                keys = ", ".join(f"{short(k)} {n}" for k, n in sorted(refused.items(), key=lambda kv: -kv[1])[:8])
                print(f"  not recorded: {sum(refused.values())} samples in batches of services the key table does not "
                      f"let write them (batch_refused; docs/security.md): {keys}")
            if stopped is not None:  # logger.max_size or min_free: the files hold the run up to there, whole
                print(f"  recording stopped at sim time {stopped.get('sim_time')} s: {stopped.get('reason')}; "
                      f"{stopped.get('after_stop', 0)} samples after it not recorded (the run went on)")
            if suspect or contested:
                top = sorted(suspect.items(), key=lambda kv: (-kv[1], kv[0]))
                keys = ", ".join(f"{short(k)} {n}" for k, n in top[:8]) + (", …" if len(top) > 8 else "")
                print(f"  recorder: {sum(suspect.values())} suspect samples ({keys or 'none'}), recorded; "
                      f"{contested} gaps not counted as lost: of writers whose id others used, or where every "
                      "sample the writers published arrived")
            if any("bagged" in v for v in counts.values()):  # logger.bag: count what the bag's files hold
                # a restarted recorder's counts are its last process's: the bag is shown, not judged
                ok = _check_bag(la.run_dir, counts, short, judge=not logger_restarted) and ok
            # Samples sent after the last one of their writer that reached the recorder (dropped, or
            # still in flight when the run stopped) leave no gap it could count: compare with what
            # every service says it published per key (final health).
            # Only a service that stopped by itself (its final health) is held to its count: one killed (SIGKILL,
            # silent, crashed) never sent what it held (its unsent batch, its queue), which no recorder can get.
            published: dict[str, int] = {}
            unfinal: dict[str, int] = {}  # the same, from the last health of services killed before their final
            killed_before_final = []
            for name, h in sorted(o.health.items()):
                into = published if h.get("final") == "1" else unfinal
                if into is unfinal and any(k.startswith("published:") for k in h):
                    killed_before_final.append(name)
                for k, v in h.items():
                    if k.startswith("published:"):
                        into[k[10:]] = into.get(k[10:], 0) + _num(v)
            unseen, unjudged = {}, 0
            for k, v in counts.items() if stopped is None else ():  # stopped: the rest was not recorded, on purpose
                own = v["received"] - v.get("suspect", 0)  # a writer's early samples come before its token:
                seen = own + v.get("lost", 0) + v.get("before_first", 0)  # unannounced, but its own
                if published.get(k, 0) > seen:
                    unseen[k] = published[k] - seen
                unjudged += max(0, published.get(k, 0) + unfinal.get(k, 0) - max(seen, published.get(k, 0)))
            if unjudged:
                print(f"  not judged: {unjudged} samples counted as published by {', '.join(killed_before_final)} "
                      "(killed before its final health) that the recorder did not get: a killed process's unsent ones")
            if unseen:
                top = sorted(unseen.items(), key=lambda kv: (-kv[1], kv[0]))
                keys = ", ".join(f"{short(k)} {n}" for k, n in top[:8]) + (", …" if len(top) > 8 else "")
                print(f"  {sum(unseen.values())} published samples never reached the recorder: {keys}")
                n_lost += sum(unseen.values())
            # realtime: what the recording missed of what was published, against logger.max_loss
            missed = n_lost
            share = missed / max(1, recv + missed)
            if realtime and not logger_restarted and stopped is None and share > sc.logger.max_loss:
                lost_share = share
                print(f"  the recording missed {share:.1%} of the samples (more than logger.max_loss, "
                      f"{sc.logger.max_loss:.1%}): a failure (--allow-loss: said, not a failure)")
            if logger_restarted:
                # what the killed recorder had received is in its part of the recording, but its
                # counts died with it, and what it had not flushed yet is lost: reported, not
                # judged (the restart policy asked for the run to go on)
                print("  (the recorder was restarted: these counts are its last process's; samples the killed "
                      "one had not written yet are lost)")
                n_lost = 0
            # realtime: a loss is reported, not a failure; lockstep promises that nothing is lost
            ok = ok and not mismatch and (realtime or not n_lost) and (realtime or not missing) and lost_share is None
        elif "logger" in o.killed:  # by a second stop signal: its counts died with it
            print("  recording summary missing (the recorder was killed)")
        else:
            print("  recording summary missing")
            ok = False
        parts = recording_parts(la.run_dir)
        if len(parts) > 1:  # split (logger.max_rrd_size, a restarted recorder): one recording for Rerun's viewer
            more = f"{len(parts) - 1} more file" + ("s" if len(parts) > 2 else "")
            print(f"  recording: {rrd} and {more} ({', '.join(p.name for p in parts[1:4])}"
                  f"{', …' if len(parts) > 4 else ''}; opened together: hilsim view {la.run_dir})")
        else:
            print(f"  recording: {rrd}")
    print(f"  logs: {la.run_dir}/")
    for name, rc in o.died:
        print(f"  service {name} died (exit code {rc})")
    if o.stalled:
        print(f"  stalled: {o.stalled}")
    if o.not_started:
        print(f"  never announced themselves: {', '.join(o.not_started)}")
    if o.faults:
        print(f"  faults reported: {len(o.faults)} (first: {o.faults[0]})")
    for r in o.restarts:
        back = f"back after {r.back_after:.1f} s" if r.back_after is not None else "not back"
        print(f"  restarted {r.name} (exit code {r.rc} at sim time {r.sim_time} s; {back})")
    if la.untrusted:
        print(f"  ignored {la.untrusted} samples on results, health and logs from writers other than the services")
    if o.killed:
        print(f"  killed (SIGKILL) on a second stop signal: {', '.join(o.killed)}")
    cut = unfinished and sc.duration is not None and o.physics_done
    if unfinished and not cut and not interrupted:
        ok = False  # the run ended without its task's result, neither by its duration nor by a signal
    targets = f" {reached_all}/{n_all} targets" if n_all else ""
    if interrupted:
        sig = signal.Signals(o.signal or signal.SIGINT)
        verdict = f"INTERRUPTED ({sig.name}){targets}" + ("" if ok else ", and FAILED (above)")
        code = 128 + sig
    elif not ok:
        verdict, code = "FAILED", EXIT_FAILED
        if lost_share is not None:
            verdict += f" (recording lost {lost_share:.1%})"
    elif cut:
        verdict, code = f"STOPPED (duration){targets}", EXIT_STOPPED
    else:
        verdict, code = "OK", EXIT_OK
    print("result: " + verdict)
    return code


def _num(v: str | None) -> int:
    """A count from a health value (0 when absent or not a number)."""
    try:
        return int(v or 0)
    except ValueError:
        return 0


def _check_bag(run_dir: Path, counts: dict[str, dict[str, int]], short: Callable[[str], str],
               judge: bool = True) -> bool:
    """The bag's messages per key, counted in its files, against what the recorder received; False
    (FAILED) if they differ (``judge``), or the bag cannot be read."""
    from hilsim.record.bag import BagError
    from hilsim.record.bag_read import BAG_DIR, key_counts

    bag = run_dir / BAG_DIR
    try:
        held = key_counts(bag)
    except BagError as e:
        print(f"  bag {bag}: NOT READABLE: {str(e).splitlines()[0]}")
        return False
    recv = sum(v.get("received", 0) for v in counts.values())
    differ = sorted(k for k in set(counts) | set(held) if held.get(k, 0) != counts.get(k, {}).get("received", 0))
    line = f"  bag: recorded {sum(held.values())} of {recv} received messages on {len(held)} topics -> {bag}"
    if not judge:
        print(line)
        return True
    if differ:
        line += "; MISMATCH (bag against received) on " + ", ".join(
            f"{short(k)} {held.get(k, 0)} of {counts.get(k, {}).get('received', 0)}" for k in differ[:8])
    print(line)
    return not differ


def _recover_recordings(run_dir: Path) -> bool:
    """After a recorder died: make each part of the run's recording complete (a SIGKILL leaves no
    RRD footer) and say what it holds; False if a part could not be recovered."""
    from hilsim.core.recording import RecordingError, contents, recording_parts, recover_rrd

    ok = True
    for part in recording_parts(run_dir):
        try:
            rewritten = recover_rrd(part)
            c = contents(part)
        except RecordingError as e:
            print(f"  recording {part}: NOT RECOVERED: {str(e).splitlines()[0]}")
            ok = False
            continue
        upto = f"up to t={c.last_sim_ns / 1e9:.3f} s sim" if c.last_sim_ns is not None else "no sim time"
        how = "the recorder was killed: recovered, verified" if rewritten else "complete, verified"
        print(f"  recording {part}: {sum(c.rows.values())} rows on {len(c.rows)} entities {upto} ({how})")
    from hilsim.record.bag import BagError
    from hilsim.record.bag_read import BAG_DIR, recover_bag

    if (run_dir / BAG_DIR).is_dir():
        try:
            for r in recover_bag(run_dir / BAG_DIR):
                how = "the recorder was killed: recovered" if r.rewritten else "complete"
                print(f"  bag {r.path}: {r.messages} messages ({how})")
        except BagError as e:
            print(f"  bag {run_dir / BAG_DIR}: NOT RECOVERED: {str(e).splitlines()[0]}")
            ok = False
    return ok
