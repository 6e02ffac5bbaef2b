"""``hilsim bench loop``'s transport floor: the three-process ring closes, measures, and leaves no process."""

from __future__ import annotations

import math
from pathlib import Path

import psutil
import pytest

from hilsim.tools.bench.ring import round_trip_us

pytestmark = pytest.mark.serial  # measurements: alone on the machine


def test_the_zenoh_ring_measures_a_round_and_its_relays_exit() -> None:
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    us = round_trip_us(rounds=50, warmup=10)
    assert math.isfinite(us) and 5.0 < us < 100_000.0  # a real round over loopback: µs to ms, not 0
    left = [p for p in psutil.Process().children(recursive=True) if p.pid not in before and p.is_running()
            and p.status() != psutil.STATUS_ZOMBIE]
    assert not left, left


def test_the_recording_floor_measures_both_sides_and_its_publisher_exits() -> None:
    from hilsim.tools.bench.ring import sample_cost_us

    before = {p.pid for p in psutil.Process().children(recursive=True)}
    c = sample_cost_us(samples=1200, tick_us=300.0)  # waits for every sample: raises if one is lost
    assert set(c) == {"callback", "channel", "put"}, c
    # receiving costs something real (a count of 0 µs would mean the samples never came)
    assert 0.5 < c["callback"] < 10_000 and 0.5 < c["channel"] < 10_000 and 0.0 <= c["put"] < 10_000, c
    left = [p for p in psutil.Process().children(recursive=True) if p.pid not in before and p.is_running()
            and p.status() != psutil.STATUS_ZOMBIE]
    assert not left, left


def test_the_distributed_run_counts_the_cpu_of_every_process(tmp_path: Path) -> None:
    """The CPU floor `hilsim bench loop` prints: every service's CPU from "ready" to the end of
    the run, read before the processes exit (a process already gone would read 0)."""
    from hilsim.tools.bench.pipeline import bench_distributed

    cpu: dict[str, float] = {}
    rtf = bench_distributed(0.5, tmp_path, cpu)
    assert set(cpu) == {"physics", "sensors", "controller", "planner", "logger", "router+launcher"}, cpu
    services = {n: s for n, s in cpu.items() if n != "router+launcher"}
    # 500 lockstep steps cost each service real CPU; together no more than the cores had in that time
    assert all(s > 0.005 for s in services.values()), cpu
    wall = 0.5 / rtf
    assert sum(cpu.values()) < (psutil.cpu_count() or 1) * (wall + 2.0), (cpu, wall)


@pytest.mark.timeout(600)  # its subprocess may take 480 s on a loaded machine (CI's default 300 s stopped it first)
def test_bench_loop_measures_every_figure_it_prints(tmp_path: Path) -> None:
    """``hilsim bench loop --json`` end to end, in its own process, with short runs: every pipeline
    ran and has a real figure, and the floors it reports are computed from what it measured."""
    import json
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "hilsim.cli", "bench", "loop", "--sim-seconds", "0.3",
                        "--realtime-seconds", "0", "--json"], capture_output=True, text=True, timeout=480)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(r.stdout)
    for k in ("bare", "in_process", "distributed", "distributed_lag1", "composed", "composed_lag1",
              "composed_recorder", "distributed_batch", "distributed_lag1_batch", "composed_batch",
              "composed_recorder_batch", "distributed_lag1_routed", "up_arm", "up_arm_batch"):
        assert math.isfinite(res[f"{k}_rtf"]) and res[f"{k}_rtf"] > 0.01, (k, res)
    assert res["ring_round_us"] > 5.0
    for k in ("up_arm", "up_arm_batch"):  # the README's run, planning included: every target reached
        u = res[k]
        assert u["rtf"] == res[f"{k}_rtf"] and u["targets"] == 3 and u["reached"] == 3 and u["task_success"], res
    dist, comp = res["distributed_cpu_us_per_step"], res["composed_cpu_us_per_step"]
    assert {"physics", "sensors", "controller", "planner", "logger"} <= set(dist), dist
    for k in ("distributed_batch", "distributed_lag1_batch", "distributed_lag1_routed"):
        assert set(res[f"{k}_cpu_us_per_step"]) == set(dist), res
    # through the run's own router every sample passes this process: it costs CPU, where the plain
    # router of the other rows, whose clients are peers, costs next to none
    assert res["distributed_lag1_routed_cpu_us_per_step"]["router+launcher"] > 5.0, res
    assert {"physics+sensors+controller", "planner", "logger"} <= set(comp), comp
    # CPU time comes in clock ticks (10 ms): the planner, which takes only its 100 Hz ticks (~20 µs a
    # step), may show 0 or 1 tick over these 300 steps; every other service costs several
    assert all(v > 1.0 for n, v in {**dist, **comp}.items() if n not in ("router+launcher", "planner")), (dist, comp)
    assert dist["planner"] >= 0.0 and comp["planner"] >= 0.0, (dist, comp)
    assert res["distributed_cpu_floor_us"] == sum(dist.values()) / res["cores"]
    assert res["composed_cores_at_10x"] == sum(comp.values()) * 10_000 / 1e6


@pytest.mark.timeout(600)
def test_bench_loop_live_measures_every_mode_against_off(tmp_path: Path) -> None:
    """``hilsim bench loop --live 1 --json`` in its own process, with short runs: every way of watching ran
    (Rerun's viewer joined; a Foxglove client to the spec took messages in) and each ratio is its run's
    real-time factor over the same round's run without it."""
    import json
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "hilsim.cli", "bench", "loop", "--live", "1", "--sim-seconds", "2",
                        "--json"], capture_output=True, text=True, timeout=540)
    assert r.returncode == 0, r.stderr[-2000:]
    live = json.loads(r.stdout)["live"]
    modes = ("off", "on", "from_start", "watched", "foxglove", "foxglove_watched")
    assert set(live["rtf"]) == set(modes), live
    for m in modes:
        assert len(live["rtf"][m]) == 1 and math.isfinite(live["rtf"][m][0]) and live["rtf"][m][0] > 0.01, live
    for m in modes[1:]:
        assert live[f"median_ratio_{m}"] == live["rtf"][m][0] / live["rtf"]["off"][0], live
    assert live["foxglove_messages"][0] > 100, live  # the arm's keys reached the client
