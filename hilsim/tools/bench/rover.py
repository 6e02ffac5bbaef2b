"""``hilsim bench rover``: the rover scenario with navigation in lockstep, its laser on and off, and the laser alone.

Zenoh keys: none of its own (the run's services').
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

from hilsim.core.scenario import load_scenario
from hilsim.tools import progress
from hilsim.tools.bench.runs import launch


def bench_laser(world: str, scans: int = 300) -> dict[str, float]:
    """The scenario's laser alone: scans (one mj_multiRay each) per wall second, from poses along x."""
    from hilsim.core import msgs
    from hilsim.launch.launcher import world_scenario
    from hilsim.sim.sensing import make_sensor

    sc = load_scenario(world_scenario("rover", world))
    laser = make_sensor("laser", sc.sensors["laser"], seed=sc.seed, dt_ns=sc.dt_ns, scenario=sc)
    truth = [msgs.Odometry(pose=msgs.PoseWithCovariance(pose=msgs.Pose(
        position=msgs.Point(x=0.01 * k, z=0.255)))) for k in range(scans)]
    t0 = time.perf_counter()
    n = 0
    for k, o in enumerate(truth):
        n = len(laser.measure(o, k * 100_000_000).ranges)
    wall = time.perf_counter() - t0
    return {"rays_per_scan": float(n), "scans_per_s": scans / wall, "rays_per_s": scans * n / wall}


def bench_rover_run(world: str, sim_seconds: float, tmp: Path, laser: bool) -> float:
    from hilsim.launch.launcher import world_scenario

    o: dict[str, Any] = {"duration": sim_seconds, "sensors.laser.enabled": laser}
    sc = load_scenario(world_scenario("rover", world), o)
    sc.services = [s for s in sc.services if s != "logger"]
    h = launch(sc, tmp / f"rover-{world}-laser-{'on' if laser else 'off'}")
    return float(h["real_time_factor"])


def cmd_rover(args: argparse.Namespace) -> int:
    """``hilsim bench rover``: the rover scenario with navigation, in lockstep.

    - ``laser_on``: ``hilsim up rover --world W`` as shipped (physics 500 Hz, encoders and IMU
      100 Hz, the 541-ray laser at 10 Hz, the four_wheel_steer controller, the navigator driving
      the task's goals; recorder off), for ``--sim-seconds``: physics' real-time factor;
    - ``laser_off``: the same with ``sensors.laser.enabled: false``: what the laser costs the loop;
    - rays per second: the laser alone, one ``mj_multiRay`` per scan from the scenario's sensor
      code (:class:`hilsim.sim.sensors_mobile.Laser`), as fast as it goes; and in the run, the rays
      the loop cast per wall second (rays per scan × scan rate × real-time factor).
    """
    logging.basicConfig(level=logging.WARNING)
    from hilsim.planning import quiet_ompl_at_exit

    quiet_ompl_at_exit()
    sim, world = args.sim_seconds, args.world
    res: dict[str, Any] = {"world": world, "sim_seconds": sim, "physics_hz": 500}
    say = progress(args.json)

    say(f"hilsim bench rover: {world} world, lockstep, navigating the task's goals, {sim:g} s sim per run")
    say("  laser alone (one mj_multiRay per scan) …")
    res["laser_alone"] = bench_laser(world)
    la = res["laser_alone"]
    say(f"    {la['rays_per_s'] / 1e6:.2f} M rays/s ({la['scans_per_s']:.0f} scans/s, "
        f"{la['rays_per_scan']:.0f} rays each)")
    on: list[float] = []
    off: list[float] = []
    with TemporaryDirectory(prefix="hilsim-bench-") as d:
        # on and off interleaved, the best of each: on a shared machine the load of the moment
        # matters more than the laser
        for k in range(args.repeat):
            say(f"  run {k + 1}/{args.repeat}: the rover scenario, laser on (physics, sensors, controller, "
                "navigator; no recorder) …")
            on.append(bench_rover_run(world, sim, Path(d) / str(k), True))
            say(f"    {on[-1]:.2f}x real time; laser off …")
            off.append(bench_rover_run(world, sim, Path(d) / str(k), False))
            say(f"    {off[-1]:.2f}x real time")
    res["laser_on_rtf"], res["laser_off_rtf"] = max(on), max(off)
    res["laser_on_runs"], res["laser_off_runs"] = on, off
    from hilsim.launch.launcher import world_scenario

    sc = load_scenario(world_scenario("rover", world))
    scan_hz = sc.sensors["laser"].rate_hz
    res["rays_per_s_in_run"] = la["rays_per_scan"] * scan_hz * res["laser_on_rtf"]
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    print(f"\nbest of {args.repeat} runs each ({sim:g} s sim)")
    print("| rover, lockstep | real-time factor | laser rays per wall second |")
    print("|---|---|---|")
    print(f"| laser on ({la['rays_per_scan']:.0f} rays at {scan_hz:g} Hz) | {res['laser_on_rtf']:.2f}x | "
          f"{res['rays_per_s_in_run']:.0f} |")
    print(f"| laser off | {res['laser_off_rtf']:.2f}x | — |")
    print(f"| laser alone (no loop) | — | {la['rays_per_s']:.0f} |")
    return 0
