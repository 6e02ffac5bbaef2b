"""``hilsim export [RUN] --to mcap|csv``: a run's Rerun recording as CSV files or as an MCAP bag (``RUN``
defaults to the latest run under ``--runs``, ``runs/``).

For runs recorded before the recorder wrote its bag (``<run>/bag/``): the ``.rrd`` holds the rows the
recorder made of the messages (decoded values, ``hilsim.record.rows``), not the messages, so what
comes back is what the rows hold. Read with Rerun's own reader (``rerun.chunk.RrdReader``, as
:func:`hilsim.core.recording.contents`); a recording without a footer (a killed recorder) reads as
far as its messages are whole.

- ``--to csv``: one file per entity path and component, ``<out>/<entity path>/<Archetype>.<field>.csv``
  (e.g. ``joints/joint_1/position/truth/Scalars.scalars.csv``), columns ``sim_time_ns`` (empty for
  static rows) and ``value`` (a number where the row holds one number, else the row as JSON), rows in
  sim-time order (static ones first; the ``.rrd``'s chunks are not in that order).
- ``--to mcap``: a rosbag2 directory (``metadata.yaml``, ``bag_0.mcap``; :mod:`hilsim.record.bag`).
  Re-encoded as ROS 2 messages (CDR) where the rows hold a message's values: ``/clock``
  (rosgraph_msgs/Clock, stamp = the row's sim time), joint states (``joints/<joint>/<q>/<source>``
  → sensor_msgs/JointState on ``/<robot>/truth/joint_states``, ``joint_states``, ``joint_commands``,
  ``controller/reference``: one message per sim time, the joints with a row at it in name order,
  the fields position/velocity/effort that were recorded; header frame_id empty) and IMU samples
  (``imu/<truth|measured>/…`` → sensor_msgs/Imu on ``/<robot>/truth/imu``, ``imu``: orientation,
  angular velocity, linear acceleration; covariances and frame_id were not recorded and are zero /
  empty). Every other entity is a JSON channel ``/rrd/<entity path>`` (``message_encoding`` json,
  a ``jsonschema`` schema): ``{"sim_time_ns": …, "<Archetype>:<field>": [...], …}`` per row, in a
  file of their own, ``rrd_rows.mcap``, which Foxglove opens beside ``bag_0.mcap``; rosbag2 and
  rosbags know only CDR (rosbags refuses a file with a ``jsonschema`` schema), so ``metadata.yaml``
  lists ``bag_0.mcap`` alone. Times: log time = publish time = the row's sim time (the recording
  keeps no receive time).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
import sys
import warnings
from collections import defaultdict
from pathlib import Path
from typing import Any

from hilsim.core import msgs
from hilsim.core.keys import Keys
from hilsim.core.recording import (
    RECORDING_NAME,
    RecordingError,
    disable_analytics,
    latest_recording,
    recording_files,
)
from hilsim.record.bag import BagError, BagWriter
from hilsim.record.bag_read import write_metadata

ROWS_FILE = "rrd_rows.mcap"  # the JSON channels, beside the bag's bag_0.mcap (not in its metadata.yaml)
JOINT_SOURCES = {"truth": "truth/joint_states", "measured": "joint_states", "command": "joint_commands",
                 "reference": "controller/reference"}
IMU_SOURCES = {"truth": "truth/imu", "measured": "imu"}
_JOINT = re.compile(r"^(?:/robots/(?P<robot>[^/]+))?/joints/(?P<joint>[^/]+)/(?P<q>position|velocity|effort)/"
                    r"(?P<src>truth|measured|command|reference)$")
_IMU = re.compile(r"^(?:/robots/(?P<robot>[^/]+))?/imu/(?P<src>truth|measured)/"
                  r"(?P<f>orientation|angular_velocity|linear_acceleration)/(?P<a>[xyzw])$")


Row = tuple[int | None, dict[str, Any]]  # (sim time ns or None for static rows, component -> value)


def read_rows(rrd: Path) -> dict[str, list[Row]]:
    """Every row of a recording per entity path, in file order: a run's ``recording.rrd`` (or its
    directory) with every part the recording was split into, in order (``recording_files``)."""
    disable_analytics()
    from rerun.chunk import RrdReader

    out: dict[str, list[Row]] = defaultdict(list)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no footer": a killed recorder's file
        for chunk in (c for f in recording_files(rrd) for c in RrdReader(f).stream().to_chunks()):
            rb = chunk.to_record_batch()
            names = [n for n in rb.schema.names if ":" in n]
            sim = rb.column("sim_time").cast("int64").to_pylist() if "sim_time" in rb.schema.names else None
            cols = {n: rb.column(n).to_pylist() for n in names}
            for i in range(chunk.num_rows):
                out[chunk.entity_path].append((sim[i] if sim is not None else None, {n: cols[n][i] for n in names}))
    return dict(out)


def _find_rrd(run: str | Path) -> Path:
    p = Path(run)
    rrd = p / RECORDING_NAME if p.is_dir() else p
    if not rrd.is_file():
        raise RecordingError(f"{run}: no recording ({rrd} does not exist)")
    return rrd


def _scalar(row: dict[str, Any]) -> float | None:
    v = row.get("Scalars:scalars")
    return float(v[0]) if isinstance(v, list) and len(v) == 1 else None


# ---------------------------------------------------------------------------------------- CSV
def _json_safe(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    if isinstance(v, list):
        return [_json_safe(x) for x in v]
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, bytes):
        return v.hex()
    return v


def export_csv(rows: dict[str, list[Row]], out: Path) -> int:
    """One CSV per entity path and component; returns the number of files."""
    n = 0
    for entity, unordered in sorted(rows.items()):
        # in sim-time order, static rows first: the .rrd's chunks are not (stable: ties stay in file order)
        rs = sorted(unordered, key=lambda row: -1 if row[0] is None else row[0])
        comps = sorted({c for _, r in rs for c in r})
        for comp in comps:
            d = out / entity.strip("/")
            d.mkdir(parents=True, exist_ok=True)
            with open(d / (comp.replace(":", ".") + ".csv"), "w", newline="") as f:
                w = csv.writer(f)
                w.writerow(["sim_time_ns", "value"])
                for t, r in rs:
                    if comp not in r or r[comp] is None:
                        continue
                    v = r[comp]
                    one = v[0] if isinstance(v, list) and len(v) == 1 and not isinstance(v[0], list | dict) else None
                    w.writerow(["" if t is None else t, one if one is not None else json.dumps(_json_safe(v))])
            n += 1
    return n


# ---------------------------------------------------------------------------------------- MCAP
def export_mcap(rows: dict[str, list[Row]], out: Path, robot: str, keys: Keys) -> dict[str, int]:
    """The bag (see the module docstring); returns messages per topic."""
    note = {"exported_from": "rrd", "times": "log_time = publish_time = the row's sim time"}
    bag = BagWriter(out, custom=note)
    json_rows = BagWriter(out, name=ROWS_FILE, custom=note)
    joints: dict[tuple[str, str], dict[int, dict[str, dict[str, float]]]] = defaultdict(lambda: defaultdict(dict))
    imus: dict[tuple[str, str], dict[int, dict[str, float]]] = defaultdict(lambda: defaultdict(dict))
    counts: dict[str, int] = defaultdict(int)
    pending: list[tuple[int, str, bytes]] = []  # (sim ns, key, payload): CDR messages, written in time order
    for entity, rs in rows.items():
        m = _JOINT.match(entity)
        if m:
            per = joints[(m["robot"] or robot, m["src"])]
            for t, r in rs:
                v = _scalar(r)
                if t is not None and v is not None:
                    per[t].setdefault(m["joint"], {})[m["q"]] = v
            continue
        m = _IMU.match(entity)
        if m:
            for t, r in rs:
                v = _scalar(r)
                if t is not None and v is not None:
                    imus[(m["robot"] or robot, m["src"])][t][f"{m['f']}.{m['a']}"] = v
            continue
        if entity == "/clock":
            for t, r in rs:
                if t is not None and _scalar(r) is not None:
                    pending.append((t, keys.clock, msgs.encode(msgs.Clock(clock=msgs.stamp(t)))))
            continue
        # any other entity: JSON rows
        ch = json_rows.json_channel(f"/rrd{entity}", f"hilsim.rrd{entity}", {"type": "object", "title": entity})
        for t, r in rs:
            data = json.dumps({"sim_time_ns": t, **_json_safe(r)}).encode()
            json_rows.add_to(ch, data, t or 0)
            counts[ch.topic] += 1
    for (who, src), per_t in joints.items():
        key = keys.for_robot(who).topic(JOINT_SOURCES[src])
        for t, per_joint in per_t.items():
            names = sorted(per_joint)
            fields = {q: [per_joint[j][q] for j in names] for q in ("position", "velocity", "effort")
                      if all(q in per_joint[j] for j in names)}
            pending.append((t, key, msgs.encode(msgs.JointState(header=msgs.header(t), name=names, **fields))))
    for (who, src), per_t in imus.items():
        key = keys.for_robot(who).topic(IMU_SOURCES[src])
        for t, v in per_t.items():
            imu = msgs.Imu(header=msgs.header(t))
            for fname in ("orientation", "angular_velocity", "linear_acceleration"):
                obj = getattr(imu, fname)
                for a in "xyzw":
                    if f"{fname}.{a}" in v:
                        setattr(obj, a, v[f"{fname}.{a}"])
            pending.append((t, key, msgs.encode(imu)))
    pending.sort(key=lambda x: x[0])
    for t, key, data in pending:
        bag.add(key, data, t)
        counts[bag.channel(key).topic] += 1
    bag.close()
    json_rows.close()
    write_metadata(out)
    return dict(counts)


def cmd_export(args: argparse.Namespace) -> int:
    try:
        if args.run is None:
            rrd = latest_recording(args.runs)
            print(f"hilsim export: the latest run, {rrd.parent}", file=sys.stderr)
        else:
            rrd = _find_rrd(args.run)
        run_dir = rrd.parent
        out = Path(args.out) if args.out else run_dir / f"export-{args.to}"
        if out.exists() and any(out.iterdir()):
            raise RecordingError(f"{out} exists and is not empty (choose another --out)")
        rows = read_rows(rrd)
    except (RecordingError, OSError, ValueError) as e:
        print(f"hilsim export: {str(e).splitlines()[0]}", file=sys.stderr)
        return 1
    if args.to == "csv":
        n = export_csv(rows, out)
        print(f"hilsim export: {n} CSV files from {sum(len(r) for r in rows.values())} rows of {len(rows)} entities "
              f"-> {out}")
        return 0
    robot, keys = _run_robot(run_dir)
    try:
        counts = export_mcap(rows, out, robot, keys)
    except BagError as e:
        print(f"hilsim export: {e}", file=sys.stderr)
        return 1
    print(f"hilsim export: {sum(counts.values())} messages on {len(counts)} topics -> {out}")
    return 0


def _run_robot(run_dir: Path) -> tuple[str, Keys]:
    """The run's robot and keys from its scenario.yaml (the arm's defaults without one)."""
    import yaml

    try:
        sc = yaml.safe_load((run_dir / "scenario.yaml").read_text()) or {}
    except (OSError, yaml.YAMLError):
        sc = {}
    robot = str(sc.get("robot", "arm"))
    ros2 = sc.get("ros2") or {}
    return robot, Keys(robot=robot, domain=int(ros2.get("domain_id", 0)),
                       namespace_template=str(ros2.get("namespace", "/{robot}")))
