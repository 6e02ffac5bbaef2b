"""``hilsim bench ros2``: the DDS half of the ROS 2 bridge, Cyclone DDS (what ``bridge-ros2-dds`` is) against
rclpy (what a bridge built as a ROS 2 node would be), measured side by side in one run.

Both bridges would take a sample from Zenoh the same way; they differ in how they hand it to DDS. So
both writers here do exactly the bridge's part: take the CDR bytes of a ``sensor_msgs/JointState`` as
they are, stamp them, and write them on ``/bench/joint_states`` (reliable, keep-last 1000), ``--count``
samples at ``--rate``; the same real ROS 2 subscriber (rclpy on rmw_fastrtps_cpp, the distribution of
``--python``) takes them.

- ``cyclone``: this process, with the bridge's own Domain configuration, type and QoS
  (:mod:`hilsim.bridges.dds_types`, :mod:`hilsim.bridges.dds_discovery`) and its raw write;
- ``rclpy``: :mod:`hilsim.tools.bench.ros2_probe` under the ROS 2 Python, ``Publisher.publish(bytes)``.

Figures per writer: CPU per sample written [µs] (process time around the writes), latency write ->
subscriber callback (p50, p99) [µs], samples delivered; and what each needs installed. DDS is made to
stay on this machine: the run happens in a network namespace of its own (root and ``ip`` needed).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import statistics
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from hilsim.core import msgs

PROBE = Path(__file__).with_name("ros2_probe.py")


def _cdr() -> bytearray:
    m = msgs.JointState(header=msgs.header(0, "base_link"), name=[f"joint_{i}" for i in range(1, 7)],
                        position=[0.1] * 6, velocity=[0.0] * 6, effort=[0.0] * 6)
    data = msgs.encode(m)
    return bytearray(data.ljust((len(data) + 3) & ~3, b"\0"))


def stamp(cdr: bytearray, t_ns: int) -> None:
    """header.stamp := t_ns (as ros2_probe does it: int32 sec, uint32 nanosec after the encapsulation)."""
    struct.pack_into("<iI", cdr, 4, t_ns // 1_000_000_000, t_ns % 1_000_000_000)


def _stats(lat_ns: list[int]) -> dict[str, float]:
    if not lat_ns:
        return {"p50_us": float("nan"), "p99_us": float("nan")}
    s = sorted(lat_ns)
    return {"p50_us": statistics.median(s) / 1000, "p99_us": s[min(len(s) - 1, int(0.99 * len(s)))] / 1000}


def _subscriber(python: str, count: int) -> subprocess.Popen[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "CYCLONEDDS"))}
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    p = subprocess.Popen([python, str(PROBE), "sub", "--count", str(count), "--seconds", "120"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    assert p.stdout is not None
    p.stdout.readline()  # {"ready": true}
    return p


def _result(p: subprocess.Popen[str]) -> dict[str, Any]:
    out, err = p.communicate(timeout=180)
    if p.returncode != 0:
        raise RuntimeError(f"the ROS 2 subscriber failed: {err.strip().splitlines()[-1:]}")
    return json.loads(out.strip().splitlines()[-1])


def _cyclone_writer(count: int, rate: float) -> float:
    """Write like bridge-ros2-dds; CPU seconds spent in the writes."""
    from cyclonedds._clayer import ddspy_write
    from cyclonedds.domain import Domain, DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.topic import Topic

    from hilsim.bridges.dds_discovery import discovery
    from hilsim.bridges.dds_types import dds_struct
    from hilsim.bridges.ros2_dds import PROFILES, dds_qos

    _domain = Domain(0, discovery({}).xml)
    dp = DomainParticipant(0)
    qos = dds_qos(dataclasses.replace(PROFILES["default"], depth=1000), ros_type="sensor_msgs/msg/JointState")
    w = DataWriter(dp, Topic(dp, "rt/bench/joint_states", dds_struct("sensor_msgs/msg/JointState")), qos=qos)
    end = time.monotonic() + 30
    while not w.get_matched_subscriptions() and time.monotonic() < end:
        time.sleep(0.05)
    time.sleep(1.0)
    cdr = _cdr()
    cpu, period, t_next = 0.0, 1.0 / rate, time.monotonic()
    for _ in range(count):
        t_next += period
        c0 = time.process_time()
        stamp(cdr, time.time_ns())
        ddspy_write(w._ref, bytes(cdr))
        cpu += time.process_time() - c0
        delay = t_next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    time.sleep(1.0)
    del w, dp, _domain
    return cpu


def _one(args: argparse.Namespace, kind: str) -> dict[str, Any]:
    """One writer's pass: ``cyclone`` (this process, as the bridge) or ``rclpy`` (the probe)."""
    python = args.python
    sub = _subscriber(python, args.count)
    if kind == "cyclone":
        cpu = _cyclone_writer(args.count, args.rate)
    else:
        env = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "CYCLONEDDS"))}
        env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
        pub = subprocess.run([python, str(PROBE), "pub", "--count", str(args.count), "--rate", str(args.rate),
                              "--cdr", _cdr().hex()], capture_output=True, text=True, env=env, timeout=180)
        if pub.returncode != 0:
            raise RuntimeError(f"the rclpy writer failed: {pub.stderr.strip().splitlines()[-1:]}")
        cpu = json.loads(pub.stdout.strip().splitlines()[-1])["cpu_s"]
    got = _result(sub)
    return {"cpu_us_per_sample": cpu / args.count * 1e6, "delivered": got["received"], **_stats(got["latency_ns"])}


def _inside(args: argparse.Namespace) -> dict[str, Any]:
    res: dict[str, Any] = {"count": args.count, "rate_hz": args.rate, "python": args.python, "repeat": args.repeat}
    runs: dict[str, list[dict[str, Any]]] = {"cyclone": [], "rclpy": []}
    for _ in range(args.repeat):  # interleaved, the least CPU of each kept: the machine's load comes and goes
        for kind in runs:
            runs[kind].append(_one(args, kind))
    for kind, rs in runs.items():
        res[kind] = min(rs, key=lambda r: r["cpu_us_per_sample"])
        res[kind]["cpu_us_all"] = [round(r["cpu_us_per_sample"], 1) for r in rs]
    res["ratio_cpu_rclpy_over_cyclone"] = res["rclpy"]["cpu_us_per_sample"] / res["cyclone"]["cpu_us_per_sample"]
    venv = Path(args.python).absolute().parent.parent  # not resolve(): bin/python links to the base Python
    size = sum((Path(d) / f).lstat().st_size for d, _, files in os.walk(venv) for f in files)  # no symlink twice
    res["install_mb"] = {"cyclone": 0.0, "rclpy": round(size / 1e6)}  # cyclonedds is a hilsim dependency already
    return res


def cmd_ros2(args: argparse.Namespace) -> int:
    if not Path(args.python).exists():
        print(f"hilsim bench ros2: --python {args.python}: no such ROS 2 Python (bash scripts/ros2-venvs.sh "
              "makes .venv-ros2/kilted and .venv-ros2/jazzy)", file=sys.stderr)
        return 2
    if args.inside:
        print(json.dumps(_inside(args)), flush=True)
        return 0
    if os.geteuid() != 0 or shutil.which("ip") is None:
        print("hilsim bench ros2: needs root and ip (iproute2): DDS runs in a network namespace of its own",
              file=sys.stderr)
        return 2
    ns = f"hsbench{os.getpid()}"
    ip = ["ip", "netns"]
    try:
        subprocess.run([*ip, "add", ns], check=True)
        for a in (["link", "set", "lo", "up"], ["link", "set", "lo", "multicast", "on"],
                  ["route", "add", "224.0.0.0/4", "dev", "lo"]):
            subprocess.run(["ip", "-n", ns, *a], check=True)
        if not args.json:
            print(f"bench ros2: {args.count} JointState samples at {args.rate:g} Hz per writer, "
                  f"subscriber {args.python} …", flush=True)
        out = subprocess.run([*ip, "exec", ns, sys.executable, "-m", "hilsim.cli", "bench", "ros2", "--inside",
                              "--python", args.python, "--count", str(args.count), "--rate", str(args.rate),
                              "--repeat", str(args.repeat)],
                             capture_output=True, text=True, timeout=600 * args.repeat)
    finally:
        subprocess.run([*ip, "del", ns], check=False)
    if out.returncode != 0:
        print(f"hilsim bench ros2: {out.stderr.strip().splitlines()[-1:] or out.stdout}", file=sys.stderr)
        return 1
    res = json.loads(out.stdout.strip().splitlines()[-1])
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    for k in ("cyclone", "rclpy"):
        r = res[k]
        print(f"  {k:8s} CPU {r['cpu_us_per_sample']:6.1f} µs/sample   latency p50 {r['p50_us']:7.0f} µs  "
              f"p99 {r['p99_us']:7.0f} µs   delivered {r['delivered']}/{res['count']}   "
              f"install {res['install_mb'][k]:.0f} MB")
    print(f"  rclpy/cyclone CPU per sample: {res['ratio_cpu_rclpy_over_cyclone']:.2f}x")
    return 0
