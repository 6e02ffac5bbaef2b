"""``hilsim bench scale``: what each more robot costs, against one robot measured in the same run.

For each number of robots N (``--robots 1,2,4,8``) and of extra subscribers S (``--subscribers
0,4``) it runs the arm scenario as ``hilsim up arm --set robots=N`` runs it (lockstep; physics,
sensors, controller, planner, recorder; no targets, so the arms hold position under 1 kHz PID)
for ``--sim-seconds`` and reports:

- the real-time factor (physics' health: sim seconds per wall second);
- the per-step latency, p50 and p99: wall time from one lockstep step to the next (the whole
  round: truth out, every robot's sensors and controller, every acknowledgement back), from
  physics' histogram (``step_p50_us``, ``step_p99_us`` in its health);
- the recorder's load: its CPU time over the run (and as a share of one core), the messages it
  recorded (``record_summary.json``) and what it still had queued when sim time ended;
- the CPU time of every service process per sim second (the whole pipeline's cost, whatever the
  number of cores);
- S extra plain Zenoh subscribers (one session each, in one helper process) on every robot's
  ``joint_states``: the samples they received, so their load is real.

With ``--repeat K`` every configuration runs K times, interleaved, and the run with the best
real-time factor is kept. Ratios are against the N = 1 run with the same S, measured in the same invocation:
``rtf_vs_1`` (the goal: 8 robots at ≥ 1/4 of one robot's real-time factor), ``cost_per_robot_vs_1``
(wall time per sim second per robot; below 1 is sub-linear), ``added_robot_cost_vs_first`` (the wall
time per sim second each robot past the first adds, against the first's; the speed issue's goal: at
most 0.5, and the largest fleet at ≥ 1x composed, ≥ 0.5x distributed: ``goal_fleet``),
``step_p50_vs_1``, ``recorder_cpu_vs_1``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

from hilsim.core.recording import read_counts
from hilsim.core.scenario import load_scenario
from hilsim.tools import progress
from hilsim.tools.bench.runs import arm_scenario, cpu_s

SERVICES = ["physics", "sensors", "controller", "planner", "logger"]


def _ints(text: str) -> list[int]:
    try:
        out = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated whole numbers, got {text!r}") from None
    if not out or any(n < 0 for n in out):
        raise argparse.ArgumentTypeError(f"expected comma-separated whole numbers >= 0, got {text!r}")
    return out


class Subscribers:
    """``n`` plain Zenoh sessions, each subscribed to ``key``, in one helper process."""

    def __init__(self, endpoint: str, key: str, n: int) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hilsim.tools.bench.scale", "--subscribe", endpoint, key, str(n)],
            stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if line.strip() != "ready":
            self.close()
            raise RuntimeError(f"extra subscribers did not start: {line.strip()!r}")

    def close(self) -> int:
        """Stop them; the samples they received in all."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            out, _ = self.proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.communicate()
            return -1
        try:
            return int(out.strip().splitlines()[-1])
        except (ValueError, IndexError):
            return -1


def _subscribe_main(endpoint: str, key: str, n: int) -> int:
    """The helper process: n sessions, a counting subscriber each, until SIGTERM; prints the total."""
    import zenoh

    from hilsim.core import transport
    from hilsim.core.config import ZenohConfig
    from hilsim.core.service import on_stop_signals

    stop = threading.Event()
    on_stop_signals(stop.set)
    counts = [0] * n
    sessions: list[zenoh.Session] = []
    subs: list[Any] = []
    for i in range(n):
        s = transport.open_session(ZenohConfig(connect=[endpoint]))

        def on(_sample: zenoh.Sample, i: int = i) -> None:
            counts[i] += 1  # a plain subscriber: takes the sample, decodes nothing

        subs.append(s.declare_subscriber(key, on))
        sessions.append(s)
    print("ready", flush=True)
    stop.wait()
    for sub in subs:
        sub.undeclare()
    for s in sessions:
        s.close()
    print(sum(counts), flush=True)
    return 0


def run_one(robots: int, subscribers: int, sim_seconds: float, tmp: Path, compose: bool,
            arrays: bool | None = None, batch: int | None = None, lag: int | None = None) -> dict[str, Any]:
    """One lockstep run of ``robots`` arms with ``subscribers`` extra subscribers: its figures.
    ``arrays``: ``fleet.arrays`` (robots as arrays, hilsim.core.fleet); ``batch``: ``logger.batch``
    (the recorder takes batches, hilsim.core.batch); ``lag``: ``clock.controller_lag``; None: as the
    scenario (``config/arm.yaml``) says."""
    from hilsim.core import transport
    from hilsim.core.keys import Keys
    from hilsim.launch.launcher import Launcher

    more: dict[str, Any] = {"robots": robots, "services": list(SERVICES)}
    if arrays is not None:
        more["fleet.arrays"] = arrays
    if batch is not None:
        more["logger.batch"] = batch
    # the arm as shipped (its controller_lag), unless asked: bench loop's arm_scenario pins lag 0
    more["clock.controller_lag"] = lag if lag is not None else load_scenario("arm").clock.controller_lag
    if compose:
        more["compose"] = [["physics", "sensors", "controller"]]
    sc = arm_scenario(sim_seconds, **more)
    run_dir = tmp / f"robots{robots}-subs{subscribers}"
    # a router of its own on a free port, said nowhere: --json's stdout is the JSON alone
    ep = f"tcp/127.0.0.1:{transport.free_port()}"
    router = transport.open_router(ep)
    subs = None
    la = Launcher(sc, run_dir, router=ep, quiet=True)
    try:
        if subscribers:
            subs = Subscribers(ep, Keys.of(sc, "*").topic("joint_states"), subscribers)
        la.start()
        if not la.wait_ready():
            raise RuntimeError(f"services did not start; see {run_dir}")
        pids = {n: c.proc.pid for n, c in la.children.items()}
        cpu0 = {n: cpu_s(p) for n, p in pids.items()}
        t0 = time.monotonic()
        la.follow(wall_timeout=900)
        wall = time.monotonic() - t0
        cpu = {n: cpu_s(p) - cpu0[n] for n, p in pids.items()}
    finally:
        la.stop()
        received = subs.close() if subs is not None else 0
        router.close()
    if la.outcome.died:
        raise RuntimeError(f"service died during the benchmark: {la.outcome.died}; see {run_dir}")
    if not la.outcome.physics_done:
        raise RuntimeError(f"the run did not reach its duration; see {run_dir}")
    ph = la.outcome.health.get("physics", {})
    counts, _ = read_counts(run_dir)
    recorded = sum(v.get("recorded", 0) for v in counts.values())
    lost = sum(v.get("lost", 0) for v in counts.values())
    rec_cpu = cpu.get("logger", 0.0)
    return {
        "robots": robots,
        "subscribers": subscribers,
        "arrays": sc.fleet.arrays,
        "batch": sc.logger.batch,
        "controller_lag": sc.clock.controller_lag,
        "rtf": float(ph["real_time_factor"]),
        "step_p50_us": float(ph.get("step_p50_us", "nan")),
        "step_p99_us": float(ph.get("step_p99_us", "nan")),
        "wall_s": wall,
        "cpu_s": sum(cpu.values()),
        "cpu_per_sim_s": sum(cpu.values()) / sim_seconds,
        "cpu_by_process": cpu,
        "recorder": {
            "cpu_s": rec_cpu,
            "cpu_pct_of_core": 100.0 * rec_cpu / wall if wall > 0 else float("nan"),
            "recorded": recorded,
            "recorded_per_sim_s": recorded / sim_seconds,
            "lost": lost,
            "queue_at_end": int(la.outcome.health.get("logger", {}).get("queue", "0") or 0),
        },
        "subscriber_samples": received,
    }


def add_ratios(runs: list[dict[str, Any]]) -> None:
    """Each run against the one-robot run with as many extra subscribers (same invocation)."""
    base = {r["subscribers"]: r for r in runs if r["robots"] == 1}
    for r in runs:
        b = base[r["subscribers"]]
        r["rtf_vs_1"] = r["rtf"] / b["rtf"]
        r["cost_per_robot_vs_1"] = (b["rtf"] / r["rtf"]) / r["robots"]
        # wall time per sim second each robot past the first adds, against the first's (sub-linear: < 1)
        r["added_robot_cost_vs_first"] = ((b["rtf"] / r["rtf"] - 1) / (r["robots"] - 1)
                                          if r["robots"] > 1 else 1.0)
        r["step_p50_vs_1"] = r["step_p50_us"] / b["step_p50_us"]
        r["cpu_per_sim_s_vs_1"] = r["cpu_per_sim_s"] / b["cpu_per_sim_s"]
        r["recorder_cpu_vs_1"] = r["recorder"]["cpu_s"] / b["recorder"]["cpu_s"] if b["recorder"]["cpu_s"] else None


def cmd_scale(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.WARNING)
    from hilsim.planning import quiet_ompl_at_exit

    quiet_ompl_at_exit()
    robots, subs, sim = sorted(set(args.robots)), sorted(set(args.subscribers)), args.sim_seconds
    if 1 not in robots or min(robots) < 1:
        print("hilsim bench scale: --robots must include 1 (the baseline) and no 0", file=sys.stderr)
        return 2
    if args.repeat < 1:
        print(f"hilsim bench scale: --repeat must be at least 1, got {args.repeat}", file=sys.stderr)
        return 2
    pipeline = "composed" if args.compose else "distributed"
    say = progress(args.json)

    lag = args.lag if args.lag is not None else load_scenario("arm").clock.controller_lag
    say(f"hilsim bench scale: arms holding position, lockstep 1 kHz (controller_lag {lag}), {sim:g} s sim per run, "
        f"robots {robots}, "
        f"extra subscribers {subs}, {pipeline} ({os.cpu_count()} CPUs)")
    # --arrays both: every configuration with fleet.arrays off and on, interleaved, reported side by side
    modes: list[bool | None] = {"scenario": [None], "off": [False], "on": [True], "both": [False, True]}[args.arrays]
    best: dict[tuple[int, int, bool | None], dict[str, Any]] = {}
    with TemporaryDirectory(prefix="hilsim-bench-scale-") as d:
        # --repeat: the rounds interleaved, the best of each kept (on a shared machine the load of
        # the moment moves the figures more than one more robot does)
        for k in range(args.repeat):
            for s in subs:
                for n in robots:
                    for a in modes:
                        rnd = f" (round {k + 1}/{args.repeat})" if args.repeat > 1 else ""
                        arr = "" if a is None else f", arrays {'on' if a else 'off'}"
                        say(f"  {n} robot{'s' if n > 1 else ''}, {s} extra subscriber{'s' if s != 1 else ''}"
                            f"{arr}{rnd} …")
                        r = run_one(n, s, sim, Path(d) / f"{k}-{a}", args.compose, a, args.batch, args.lag)
                        if (n, s, a) not in best or r["rtf"] > best[n, s, a]["rtf"]:
                            best[n, s, a] = r
                        say(f"    {r['rtf']:.3f}x real time, step p50 {r['step_p50_us']:.0f} µs, p99 "
                            f"{r['step_p99_us']:.0f} µs; recorder {r['recorder']['cpu_pct_of_core']:.0f} % of a core, "
                            f"{r['recorder']['recorded']} messages")
    results = [_results([best[n, s, a] for s in subs for n in robots], args, pipeline) for a in modes]
    res = dict(results[-1])  # the last mode's (arrays on, with --arrays both) at the top level, as always
    if len(results) > 1:
        res["by_arrays"] = {"on" if r["runs"][0]["arrays"] else "off": r for r in results}
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    for r in results:
        if len(results) > 1:
            print(f"\nfleet.arrays: {'on' if r['runs'][0]['arrays'] else 'off'}")
        _print(r, args, pipeline)
    return 0


def _results(runs: list[dict[str, Any]], args: argparse.Namespace, pipeline: str) -> dict[str, Any]:
    """The figures of one set of runs (one per robots × subscribers), its ratios and goals."""
    robots, subs, sim = sorted(set(args.robots)), sorted(set(args.subscribers)), args.sim_seconds
    add_ratios(runs)
    res: dict[str, Any] = {
        "sim_seconds": sim, "pipeline": pipeline, "robots": robots, "subscribers": subs, "repeat": args.repeat,
        "arrays": runs[0]["arrays"],
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "runs": runs,
    }
    top = max(robots)
    goal = {}
    for s in subs:
        r = next(r for r in runs if r["robots"] == top and r["subscribers"] == s)
        goal[str(s)] = {"robots": top, "rtf_vs_1": r["rtf_vs_1"], "met": r["rtf_vs_1"] >= 0.25}
    res["goal_rtf_vs_1_at_least_0.25"] = goal
    # the speed issue's goals for the largest fleet: its real-time factor (composed >= 1x, distributed
    # >= 0.5x) and what each robot past the first costs (<= 0.5 of the first), with no extra subscribers
    r0 = next((r for r in runs if r["robots"] == top and r["subscribers"] == min(subs)), None)
    need = 1.0 if args.compose else 0.5
    res["goal_fleet"] = {"robots": top, "rtf": r0["rtf"], "rtf_goal": need, "rtf_met": r0["rtf"] >= need,
                         "added_robot_cost_vs_first": r0["added_robot_cost_vs_first"],
                         "added_cost_met": r0["added_robot_cost_vs_first"] <= 0.5} if r0 and top > 1 else None
    return res


def _print(res: dict[str, Any], args: argparse.Namespace, pipeline: str) -> None:
    sim = args.sim_seconds
    print(f"\n{'best of ' + str(args.repeat) + ' runs each, ' if args.repeat > 1 else ''}{sim:g} s sim per run")
    print("| robots | extra subs | real-time factor | vs 1 robot | cost per robot vs 1 | step p50 / p99 [µs] "
          "| CPU s per sim s | recorder CPU (% core) | recorded msgs |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in res["runs"]:
        print(f"| {r['robots']} | {r['subscribers']} | {r['rtf']:.3f}x | {r['rtf_vs_1']:.3f} | "
              f"{r['cost_per_robot_vs_1']:.3f} | {r['step_p50_us']:.0f} / {r['step_p99_us']:.0f} | "
              f"{r['cpu_per_sim_s']:.2f} | {r['recorder']['cpu_pct_of_core']:.0f} | {r['recorder']['recorded']} |")
    for s, g in res["goal_rtf_vs_1_at_least_0.25"].items():
        print(f"goal {g['robots']} robots at >= 1/4 of one robot's real-time factor ({s} extra subscribers): "
              f"{g['rtf_vs_1']:.3f} — {'met' if g['met'] else 'NOT met'}")
    f = res["goal_fleet"]
    if f:
        print(f"goal {f['robots']} robots at >= {f['rtf_goal']:g}x real time ({pipeline}): {f['rtf']:.3f}x — "
              f"{'met' if f['rtf_met'] else 'NOT met'}; each robot past the first costs "
              f"{f['added_robot_cost_vs_first']:.3f} of the first (goal <= 0.5) — "
              f"{'met' if f['added_cost_met'] else 'NOT met'}")


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "--subscribe":
        sys.exit(_subscribe_main(sys.argv[2], sys.argv[3], int(sys.argv[4])))
    sys.exit("usage: python -m hilsim.tools.bench.scale --subscribe ENDPOINT KEY N (hilsim bench scale's helper)")
