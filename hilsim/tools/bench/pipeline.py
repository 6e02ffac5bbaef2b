"""``hilsim bench loop``: how fast the distributed arm pipeline runs, against limits measured in the same run.

Three lockstep figures, each the real-time factor (sim seconds per wall second) of the arm
holding position under 1 kHz PID control with its sensors:
- ``distributed``: ``hilsim up arm`` — five processes over Zenoh, logger recording;
- ``in_process``: the *same service code* (physics, sensors, controller, planner) wired through
  :class:`hilsim.core.inproc.Bus` in one process — CDR encoding kept, Zenoh and processes removed;
- ``bare``: MuJoCo and the PID arrays alone, no messages at all;
- ``composed``: ``hilsim up arm --compose physics,sensors,controller`` — those three in one
  process (:mod:`hilsim.launch.compose`), planner and logger separate, recording everything;
- ``distributed_lag1``, ``composed_lag1``: the same with ``clock.controller_lag: 1`` (the pipelined
  lockstep: the controller's command acts one step after the measurement it answers);
- ``distributed_batch``, ``distributed_lag1_batch``, ``composed_batch``, ``composed_recorder_batch``: those
  with the recorder taking batches (``logger.batch``: ``BATCH`` samples per batch; docs/recording.md),
  the distributed ones with their CPU per step and process too.
Ratios are distributed / in_process and distributed / bare: compare ratios, not absolute times.

``ring``: a bare zenoh-python ring of three processes (:mod:`hilsim.tools.bench.ring`), the transport floor
of one distributed step; the distributed step time is reported against ring round + in-process
step time. The CPU floor: the CPU every process of the distributed run spends per step (psutil,
from "ready" to the end of the run), divided by the machine's cores: on a small machine the
distributed pipeline is CPU-bound, and no step can take less wall time than that. Likewise the
composed run's CPU per step, as the cores it would need at 10x real time.

``distributed_lag1_routed``: ``distributed_lag1`` as ``hilsim up`` runs it. The rows above use a plain
router, so the services are peers and also reach each other directly. Here the run has its own
router with a user and password, every service is a client of it, and every sample passes through
it. Its CPU per step includes the router's (this process).

``up_arm``, ``up_arm_batch``: the README's run, ``hilsim up arm`` as shipped (its own router, its
three targets planned and driven, recording), without and with batches: the real-time factor of
the whole run, planning included, and the targets reached.

Then ``realtime``: the same pipeline with ``--clock realtime`` for ``--realtime-seconds``;
physics reports its tick jitter (p50, p99) and the share of missed deadlines.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import time
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import numpy as np
import psutil

from hilsim.core.scenario import load_scenario
from hilsim.tools import progress
from hilsim.tools.bench.live import bench_live
from hilsim.tools.bench.runs import arm_scenario, launch, run_arm

BATCH = 256  # logger.batch of the *_batch pipelines


def bench_bare(sim_seconds: float) -> float:
    """MuJoCo + PID arrays in one loop: the floor of any implementation."""
    from hilsim.sim import control
    from hilsim.sim.world import World

    sc = arm_scenario(sim_seconds)
    w = World(sc)
    gains = control.gains_for(sc.controller.gains, w.joint_names)
    pids = [control.Pid(g, -float(w.effort_limit[i]), float(w.effort_limit[i])) for i, g in enumerate(gains)]
    ref = w.positions()
    steps = round(sim_seconds / sc.clock.dt)
    t0 = time.perf_counter()
    for _ in range(steps):
        q, v = w.positions(), w.velocities()
        u = [p.update(r, 0.0, a, b, sc.clock.dt) for p, r, a, b in zip(pids, ref, q, v, strict=True)]
        w.command_array(np.array(u))
        w.step()
    return sim_seconds / (time.perf_counter() - t0)


def bench_in_process(sim_seconds: float) -> float:
    """The services' own code, one process, no transport."""
    from hilsim.core.inproc import Bus
    from hilsim.core.registry import service_class

    sc = arm_scenario(sim_seconds, services=["physics", "sensors", "controller", "planner"])
    bus = Bus()
    svcs = {n: service_class(n)(sc) for n in ("sensors", "controller", "planner", "physics")}
    for s in svcs.values():
        s.attach(bus.session())
    phys = svcs["physics"]
    phys.fix_participants()
    t0 = time.perf_counter()
    with phys.lock:
        phys.started = True
        phys.wall_start = time.monotonic()
        phys._publish_step()
    bus.drain(until=lambda: phys.done)
    wall = time.perf_counter() - t0
    if not phys.done:
        raise RuntimeError(f"in-process pipeline stalled at t={phys.world.time_ns / 1e9:.3f}s "
                           f"waiting for {phys._missing()}")
    for s in svcs.values():
        s.request_stop()
        s.teardown()
    return sim_seconds / wall


def bench_up_arm(tmp: Path, batch: int = 0) -> dict[str, float]:
    """The README's run: ``hilsim up arm`` as shipped (its targets planned and driven, lag 1,
    recording everything); ``batch``: ``logger.batch``. Physics' real-time factor over the whole
    run (planning included: in lockstep a plan takes wall time, no sim time), and the targets reached
    as the planner's results say, against the task's."""
    sc = load_scenario("arm", {"logger.batch": batch})
    o = run_arm(sc, tmp / f"up-arm-batch{batch}", task=True, run_router=True)
    reached = sum(1 for r in o.results if r.success and r.goal_id.startswith("task-"))  # as the summary counts
    return {"rtf": float(o.health.get("physics", {})["real_time_factor"]), "reached": float(reached),
            "targets": float(len(sc.task.targets)), "task_success": float(bool(o.task.success))}


def bench_distributed(sim_seconds: float, tmp: Path, cpu: dict[str, float] | None = None, bag: bool = True,
                      batch: int = 0) -> float:
    """``hilsim up arm``; ``bag``: the recorder writes its bag too (``logger.bag``); ``batch``: ``logger.batch``."""
    name = ("distributed" if bag else "distributed-nobag") + (f"-batch{batch}" if batch else "")
    h = launch(arm_scenario(sim_seconds, **{"logger.bag": bag, "logger.batch": batch}), tmp / name, cpu)
    return float(h["real_time_factor"])


def bench_composed(sim_seconds: float, tmp: Path, with_recorder: bool = False,
                   cpu: dict[str, float] | None = None, lag: int = 0, batch: int = 0) -> float:
    """Physics, sensors and controller in one process (hilsim.launch.compose), the planner separate, recording
    everything; ``with_recorder``: the recorder in that process too (its samples never cross Zenoh);
    ``lag``: ``clock.controller_lag``; ``batch``: ``logger.batch``."""
    group = ["physics", "sensors", "controller", *(["logger"] if with_recorder else [])]
    h = launch(arm_scenario(sim_seconds, compose=[group], **{"clock.controller_lag": lag, "logger.batch": batch}),
                tmp / ("+".join(group) + f"-lag{lag}" + (f"-batch{batch}" if batch else "")), cpu)
    return float(h["real_time_factor"])


def bench_pipelined(sim_seconds: float, tmp: Path, cpu: dict[str, float] | None = None, batch: int = 0,
                    run_router: bool = False, per_service: bool = True) -> float:
    """``hilsim up arm`` with ``clock.controller_lag: 1``: physics steps on while sensors and
    controller work on the step before (the pipelined lockstep, docs/keys.md); ``batch``: ``logger.batch``;
    ``run_router``: through the run's own router, as ``hilsim up`` runs it (see
    :func:`hilsim.tools.bench.runs.run_arm`)."""
    name = ("distributed-lag1" + (f"-batch{batch}" if batch else "") + ("-routed" if run_router else "")
            + ("" if per_service else "-one-identity"))
    h = launch(arm_scenario(sim_seconds, **{"clock.controller_lag": 1, "logger.batch": batch}), tmp / name,
                cpu, run_router=run_router, per_service=per_service)
    return float(h["real_time_factor"])


def bench_identities(sim_seconds: float, tmp: Path, repeat: int, say: Any) -> dict[str, Any]:
    """What an identity per process costs (docs/security.md): the pipelined arm through the run's own
    router with one identity that may do everything (as before) and with one per process, alternated
    ``repeat`` times in one sitting (a shared machine's load drifts: each pair's ratio, and their median)."""
    one, each, ratios, router_one, router_each = [], [], [], [], []
    steps = sim_seconds * 1000
    for i in range(repeat):
        ca: dict[str, float] = {}
        cb: dict[str, float] = {}
        a = bench_pipelined(sim_seconds, tmp / f"id{i}", ca, run_router=True, per_service=False)
        b = bench_pipelined(sim_seconds, tmp / f"id{i}", cb, run_router=True, per_service=True)
        one.append(a)
        each.append(b)
        ratios.append(b / a)
        # the router checks every sample against its access control: its CPU per step (in this process)
        router_one.append(1e6 * ca["router+launcher"] / steps)
        router_each.append(1e6 * cb["router+launcher"] / steps)
        say(f"    pair {i + 1}: one identity {a:.3f}x, one per process {b:.3f}x real time (ratio {b / a:.3f}); "
            f"router+launcher {router_one[-1]:.0f} vs {router_each[-1]:.0f} µs of CPU per step")
    return {"one_identity_rtf": one, "per_process_rtf": each, "ratios": ratios,
            "median_ratio": float(statistics.median(ratios)), "router_us_one_identity": router_one,
            "router_us_per_process": router_each}


def bench_realtime(seconds: float, tmp: Path) -> dict[str, float]:
    h = launch(arm_scenario(seconds, **{"clock.mode": "realtime"}), tmp / "realtime")
    return {
        "jitter_p50_ms": float(h["jitter_p50_us"]) / 1e3,
        "jitter_p99_ms": float(h["jitter_p99_us"]) / 1e3,
        "missed_pct": 100.0 * float(h["overruns"]) / max(float(h["steps"]), 1.0),
        "steps": float(h["steps"]),
    }


def _each(us_per_step: dict[str, float]) -> str:
    """``name µs, …``, costliest first."""
    return ", ".join(f"{n} {v:.0f}" for n, v in sorted(us_per_step.items(), key=lambda x: -x[1]))


def _recorder_line(r: dict[str, float]) -> str:
    """The recorder's CPU per sample without and with the bag: whole process and worker alone."""
    p0, p1 = r["process_without_bag_us"], r["process_with_bag_us"]
    w0, w1 = r["worker_without_bag_us"], r["worker_with_bag_us"]
    return (f"{p0:.1f} µs of CPU per recorded sample without the bag, {p1:.1f} µs with it "
            f"({100 * (p1 / p0 - 1):+.0f} %; logger process, distributed run); "
            f"its worker alone {w0:.2f} -> {w1:.2f} µs "
            f"({100 * (w1 / w0 - 1):+.0f} %, {r['worker_samples']:.0f} samples of the arm mix)")


def cmd_loop(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.WARNING)
    sim = args.sim_seconds
    res: dict[str, Any] = {"sim_seconds": sim, "control_hz": 1000}
    say = progress(args.json)

    say(f"hilsim bench loop: arm, 1 kHz physics and control, {sim:g} s sim per lockstep run")
    if getattr(args, "live", 0):
        say(f"  watching it live: the pipelined arm through the run's own router, without --view, with it, with "
            f"it streaming from the start, with Rerun's viewer joined, and with Foxglove's server alone and "
            f"watched, {args.live} rounds …")
        with TemporaryDirectory(prefix="hilsim-bench-") as d:
            res["live"] = r = bench_live(sim, Path(d), args.live, say)
        say(f"    median ratio against off: on (nobody watching) {r['median_ratio_on']:.3f}, streaming from the "
            f"start (nobody watching) {r['median_ratio_from_start']:.3f}, watched {r['median_ratio_watched']:.3f}"
            + (f", foxglove {r['median_ratio_foxglove']:.3f}, foxglove watched "
               f"{r['median_ratio_foxglove_watched']:.3f}" if "median_ratio_foxglove" in r else ""))
        if args.json:
            print(json.dumps(res, indent=1))
        return 0
    if getattr(args, "identities", 0):
        say(f"  identities: the pipelined arm through the run's own router, one identity vs one per process, "
            f"{args.identities} pairs …")
        with TemporaryDirectory(prefix="hilsim-bench-") as d:
            res["identities"] = r = bench_identities(sim, Path(d), args.identities, say)
        say(f"    median ratio (one per process / one identity): {r['median_ratio']:.3f}")
        if args.json:
            print(json.dumps(res, indent=1))
        return 0
    say("  bare (MuJoCo + PID, no messages) …")
    res["bare_rtf"] = bench_bare(sim)
    say(f"    {res['bare_rtf']:.2f}x real time")
    say("  in-process (same service code, no Zenoh) …")
    res["in_process_rtf"] = bench_in_process(sim)
    say(f"    {res['in_process_rtf']:.2f}x real time")
    say("  transport floor: a bare zenoh-python ring of three processes …")
    from hilsim.tools.bench.ring import PAYLOAD_BYTES, round_trip_us

    res["ring_round_us"] = round_trip_us()
    say(f"    {res['ring_round_us']:.0f} µs per round ({PAYLOAD_BYTES}-byte payloads, median)")
    say("  recording floor: CPU per sample sent to another process …")
    from hilsim.tools.bench.ring import KEYS_PER_STEP, sample_cost_us

    res["sample_cost_us"] = c = sample_cost_us()
    say(f"    receiver {c['callback']:.1f} µs (callback), {c['channel']:.1f} µs (FIFO channel); "
        f"sender {c['put']:.1f} µs")
    with TemporaryDirectory(prefix="hilsim-bench-") as d:
        say("  distributed (5 processes over Zenoh, logging on) …")
        cpu: dict[str, float] = {}
        res["distributed_rtf"] = bench_distributed(sim, Path(d), cpu)
        steps = sim * 1000
        res["distributed_cpu_us_per_step"] = {n: 1e6 * s / steps for n, s in cpu.items()}
        say(f"    {res['distributed_rtf']:.2f}x real time")
        say("  the recorder's CPU per sample, without and with its bag (logger.bag false/true) …")
        from hilsim.tools.bench.bag import process_us_per_sample, worker_cost

        cpu_nobag: dict[str, float] = {}
        bench_distributed(sim, Path(d), cpu_nobag, bag=False)
        res["recorder"] = {
            "process_without_bag_us": process_us_per_sample(Path(d) / "distributed-nobag", cpu_nobag["logger"]),
            "process_with_bag_us": process_us_per_sample(Path(d) / "distributed", cpu["logger"]),
            **{f"worker_{k}": v for k, v in worker_cost().items()},
        }
        say(f"    {_recorder_line(res['recorder'])}")
        say("  distributed, pipelined (clock.controller_lag 1: the controller acts one step later) …")
        cpu = {}
        res["distributed_lag1_rtf"] = bench_pipelined(sim, Path(d), cpu)
        res["distributed_lag1_cpu_us_per_step"] = {n: 1e6 * s / steps for n, s in cpu.items()}
        say(f"    {res['distributed_lag1_rtf']:.2f}x real time")
        say("  composed (physics, sensors, controller in one process; planner and logger apart) …")
        cpu = {}
        res["composed_rtf"] = bench_composed(sim, Path(d), cpu=cpu)
        res["composed_cpu_us_per_step"] = {n: 1e6 * s / steps for n, s in cpu.items()}
        say(f"    {res['composed_rtf']:.2f}x real time")
        say("  composed, pipelined (clock.controller_lag 1) …")
        res["composed_lag1_rtf"] = bench_composed(sim, Path(d), lag=1)
        say(f"    {res['composed_lag1_rtf']:.2f}x real time")
        say("  composed with the recorder (physics, sensors, controller, logger in one process) …")
        res["composed_recorder_rtf"] = bench_composed(sim, Path(d), with_recorder=True)
        say(f"    {res['composed_recorder_rtf']:.2f}x real time")
        say(f"  the same recording pipelines with the recorder taking batches (logger.batch {BATCH}) …")
        cpu = {}
        res["distributed_batch_rtf"] = bench_distributed(sim, Path(d), cpu, batch=BATCH)
        res["distributed_batch_cpu_us_per_step"] = {n: 1e6 * s / steps for n, s in cpu.items()}
        say(f"    distributed {res['distributed_batch_rtf']:.2f}x real time")
        cpu = {}
        res["distributed_lag1_batch_rtf"] = bench_pipelined(sim, Path(d), cpu, batch=BATCH)
        res["distributed_lag1_batch_cpu_us_per_step"] = {n: 1e6 * s / steps for n, s in cpu.items()}
        say(f"    distributed, pipelined {res['distributed_lag1_batch_rtf']:.2f}x real time")
        res["composed_batch_rtf"] = bench_composed(sim, Path(d), batch=BATCH)
        say(f"    composed {res['composed_batch_rtf']:.2f}x real time")
        res["composed_recorder_batch_rtf"] = bench_composed(sim, Path(d), with_recorder=True, batch=BATCH)
        say(f"    composed with the recorder {res['composed_recorder_batch_rtf']:.2f}x real time")
        say("  distributed, pipelined, through the run's own router (as hilsim up runs it: every sample "
            "via the router) …")
        cpu = {}
        res["distributed_lag1_routed_rtf"] = bench_pipelined(sim, Path(d), cpu, run_router=True)
        res["distributed_lag1_routed_cpu_us_per_step"] = {n: 1e6 * s / steps for n, s in cpu.items()}
        say(f"    {res['distributed_lag1_routed_rtf']:.2f}x real time")
        say("  the README's run: hilsim up arm as shipped (planning included), and with batches …")
        for k, b in (("up_arm", 0), ("up_arm_batch", BATCH)):
            r = bench_up_arm(Path(d), batch=b)
            res[f"{k}_rtf"], res[k] = r["rtf"], r
            say(f"    {k}: {r['rtf']:.2f}x real time, {r['reached']:.0f}/{r['targets']:.0f} targets reached")
        if args.realtime_seconds > 0:
            say(f"  realtime mode for {args.realtime_seconds:g} s …")
            res["realtime"] = bench_realtime(args.realtime_seconds, Path(d))
    res["ratio_distributed_vs_in_process"] = res["distributed_rtf"] / res["in_process_rtf"]
    # per 1 ms step: what the distributed pipeline spends against its floor (one ring round for the
    # three hops of a step, plus the services' own work as measured in one process)
    step_us = {k: 1000.0 / res[f"{k}_rtf"] for k in ("distributed", "in_process", "composed")}
    res["step_us"] = step_us
    res["ratio_distributed_vs_floor"] = step_us["distributed"] / (res["ring_round_us"] + step_us["in_process"])
    res["ratio_distributed_vs_bare"] = res["distributed_rtf"] / res["bare_rtf"]
    # the distributed pipeline is CPU-bound on a small machine: the CPU all its processes spend per
    # step, spread over every core, is a floor of its own besides the ring's latency; and what the
    # composed run would need at 10x: the CPU of one step, 10 000 steps a second
    cores = psutil.cpu_count() or 1
    res["cores"] = cores
    res["distributed_cpu_floor_us"] = sum(res["distributed_cpu_us_per_step"].values()) / cores
    res["composed_cores_at_10x"] = sum(res["composed_cpu_us_per_step"].values()) * 10_000 / 1e6
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    print()
    print("| pipeline | real-time factor | vs in-process | vs bare |")
    print("|---|---|---|---|")
    for k in ("bare", "in_process", "distributed", "distributed_lag1", "composed", "composed_lag1",
              "composed_recorder", "distributed_batch", "distributed_lag1_batch", "composed_batch",
              "composed_recorder_batch", "distributed_lag1_routed", "up_arm", "up_arm_batch"):
        v = res[f"{k}_rtf"]
        print(f"| {k} | {v:.2f}x | {v / res['in_process_rtf']:.3f} | {v / res['bare_rtf']:.3f} |")
    fl = res["ring_round_us"] + step_us["in_process"]
    print(f"\nper step: distributed {step_us['distributed']:.0f} µs, floor {fl:.0f} µs (ring round "
          f"{res['ring_round_us']:.0f} + in-process {step_us['in_process']:.0f}): ratio "
          f"{res['ratio_distributed_vs_floor']:.2f} (goal <= 1.5); composed {step_us['composed']:.0f} µs")
    dist, comp = res["distributed_cpu_us_per_step"], res["composed_cpu_us_per_step"]
    print(f"distributed CPU per step, all processes: {sum(dist.values()):.0f} µs = "
          f"{res['distributed_cpu_floor_us']:.0f} µs of wall time on {cores} cores at the least ({_each(dist)})")
    for k in ("distributed_lag1", "distributed_batch", "distributed_lag1_batch", "distributed_lag1_routed"):
        each = res[f"{k}_cpu_us_per_step"]
        print(f"{k} CPU per step, all processes: {sum(each.values()):.0f} µs ({_each(each)})")
    print(f"composed CPU per step, all processes: {sum(comp.values()):.0f} µs: at 10x real time that is "
          f"{res['composed_cores_at_10x']:.2f} cores of this machine's {cores} ({_each(comp)})")
    c = res["sample_cost_us"]
    per_s = KEYS_PER_STEP * 1000 * 10 * (min(c["callback"], c["channel"]) + c["put"]) / 1e6
    print(f"recording floor: a recorder in its own process costs {min(c['callback'], c['channel']):.1f} + "
          f"{c['put']:.1f} µs of CPU per sample on Zenoh alone; at 10x real time the arm's "
          f"{KEYS_PER_STEP} keys per step take {per_s:.2f} cores for it")
    print(f"recorder: {_recorder_line(res['recorder'])}")
    if "realtime" in res:
        r = res["realtime"]
        print(f"\nrealtime 1 kHz, {args.realtime_seconds:g} s: tick jitter p50 {r['jitter_p50_ms']:.3f} ms, "
              f"p99 {r['jitter_p99_ms']:.3f} ms, missed deadlines {r['missed_pct']:.3f} % of {r['steps']:.0f} steps")
    best_d = max(res["distributed_rtf"], res["distributed_lag1_rtf"])
    best_c = max(res["composed_rtf"], res["composed_lag1_rtf"])
    print(f"goal >= 3x real time distributed: {'met' if best_d >= 3 else 'NOT met'} ({best_d:.2f}x, best of lag 0/1)")
    print(f"goal >= 10x real time composed: {'met' if best_c >= 10 else 'NOT met'} ({best_c:.2f}x, best of lag 0/1)")
    for k in ("up_arm", "up_arm_batch"):
        u = res[k]
        every = u["reached"] == u["targets"] and u["task_success"]
        print(f"goal >= 2x real time hilsim up arm ({'as shipped' if k == 'up_arm' else f'logger.batch {BATCH}'}, "
              f"planning included): {'met' if u['rtf'] >= 2 and every else 'NOT met'} ({u['rtf']:.2f}x, "
              f"{u['reached']:.0f}/{u['targets']:.0f} targets reached)")
    return 0
