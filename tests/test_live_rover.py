"""The rover, live (``hilsim up rover-outdoor --view --foxglove PORT``, lockstep): one run, watched by two clients
neither of which the project wrote, judged by the run's bag (rosbag2 MCAP, read by ``mcap``/``mcap_ros2``) and by
the physics truth in it (``/rover/truth/odom``).

- Rerun's own client (``rerun --connect GRPC --save FILE``), joined as a viewer (``live_viewer.join``; the run
  starts its physics only then): the saved stream, read with Rerun's ``RrdReader``, carries while the rover drives
  the laser scan (``/scan``, Points3D: each row the finite ranges of the bag's scan of that sim time), the GPS
  (``/geo/gps/<k>``, GeoPoints: each row's newest point the bag's fix of that time) and the map (``/map``, a
  textured Mesh3D: the bag's occupancy grid, its size, place and occupied cells darker than free ones), and the
  rover's pose (``/tf/base_link``, Transform3D world -> chassis) is the truth's at the same sim time.
- A Foxglove client written here to the protocol's spec (``websockets``) subscribes to ``/rover/scan``,
  ``/rover/odom``, ``/rover/gps/fix``, ``/rover/map`` and ``/tf``: the schemas advertised are the ROS 2 types;
  every message is decoded by ``mcap_ros2`` (from the advertised ``ros2msg`` schema) and by ``rosbags``' Jazzy
  types, and the two agree; each is byte for byte a message of the bag on that topic; the scan has the
  configured fov/resolution's rays; ``/tf``'s world -> chassis transform is the truth of its stamp, the GPS fixes
  are the antenna's true place (the truth and ``/tf``'s chassis -> ``gps``) within the sensor's configured error,
  and the odometry estimate stays near the truth.
- The run ends ``result: OK`` with its target reached (the truth within 0.2 m of it).
"""

from __future__ import annotations

import json
import math
import os
import signal
import struct
import subprocess
import threading
import time
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from util import REPO, foxglove_subscribe, up

from hilsim.core import transport
from hilsim.core.recording import rerun_env, rerun_executable
from hilsim.core.scenario import load_scenario
from hilsim.record import live, live_viewer

SCENARIO = REPO / "config" / "rover-outdoor.yaml"
TARGET = (8.0, 4.0, 0.0)  # the outdoor task's first goal, round rock_1: ~15 s of sim time, ~9 m of driving
TYPES = {"/rover/scan": "sensor_msgs/msg/LaserScan", "/rover/odom": "nav_msgs/msg/Odometry",
         "/rover/gps/fix": "sensor_msgs/msg/NavSatFix", "/rover/map": "nav_msgs/msg/OccupancyGrid",
         "/tf": "tf2_msgs/msg/TFMessage"}
BAG_TOPICS = [*TYPES, "/rover/truth/odom"]
GOAL_TOLERANCE = 0.2  # [m] a goal is reached by the truth within this (test_rover_nav_e2e's, the issue's)
# Rerun stores a Transform3D's translation and quaternion as float32: a coordinate under 16 m is rounded by at
# most 1e-6 m, a quaternion's component by 6e-8; ten times that is the truth, a step's motion (~2 mm) is not
F32_M, F32_Q = 1e-5, 1e-6


def _ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _bag(run: Path) -> tuple[dict[str, dict[int, Any]], dict[str, set[bytes]]]:
    """The run's bag: the decoded messages of some topics by stamp (not /tf: many a stamp), and every topic's
    raw CDR payloads."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    decoded: dict[str, dict[int, Any]] = {t: {} for t in BAG_TOPICS if t != "/tf"}
    raw: dict[str, set[bytes]] = {t: set() for t in BAG_TOPICS}
    factory, decoders = DecoderFactory(), {}
    for f in sorted((run / "bag").glob("*.mcap")):
        with open(f, "rb") as fh:
            for schema, channel, message in make_reader(fh).iter_messages(topics=BAG_TOPICS):
                raw[channel.topic].add(message.data)
                if channel.topic in decoded:
                    dec = decoders.get(schema.id) or decoders.setdefault(
                        schema.id, factory.decoder_for(channel.message_encoding, schema))
                    m = dec(message.data)
                    decoded[channel.topic][_ns(m.header)] = m
    return decoded, raw


def _live_rows(path: Path) -> dict[str, list[tuple[int, dict[str, Any]]]]:
    """What Rerun's client saved: the rows on the sim-time timeline of the entities checked here, as
    (sim time [ns], {component: value}), by entity."""
    import pyarrow as pa
    from rerun.chunk import RrdReader  # rerun 0.41's reader, as tests/test_live_browser.py reads its client's file

    out: dict[str, list[tuple[int, dict[str, Any]]]] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no footer", should the client have been stopped
        for chunk in RrdReader(path).stream().to_chunks():
            e = chunk.entity_path
            if not (e in ("/scan", "/map", "/tf/base_link") or e.startswith("/geo/gps/")):
                continue
            rb = chunk.to_record_batch()
            if "sim_time" not in rb.schema.names:
                continue  # the entity's static style (colour, radius)
            times = rb.column("sim_time").cast(pa.int64()).to_pylist()
            cols = {n: rb.column(n).to_pylist() for n in rb.schema.names if ":" in n}
            out.setdefault("/geo/gps" if e.startswith("/geo/gps/") else e, []).extend(
                (t, {n: c[i] for n, c in cols.items()}) for i, t in enumerate(times))
    return out


def _rotate(q: Any, v: tuple[float, float, float]) -> np.ndarray:
    """A vector rotated by a ROS quaternion (scipy's rotation, not the project's)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat([q.x, q.y, q.z, q.w]).apply(v)


def _yaw(q: Any) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


class FoxgloveClient(threading.Thread):
    """A client written to Foxglove's WebSocket protocol spec: subscribes to the wanted topics as they are
    advertised and keeps every message's payload, until the server closes (it stops with the run)."""

    def __init__(self, url: str) -> None:
        super().__init__(daemon=True)
        self.url = url
        self.connected = threading.Event()
        self.channels: dict[str, dict[str, Any]] = {}
        self.got: dict[str, list[bytes]] = {t: [] for t in TYPES}
        self.error: BaseException | None = None

    def run(self) -> None:
        import websockets.exceptions
        import websockets.sync.client as ws_client

        try:
            with ws_client.connect(self.url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],  # type: ignore[list-item]
                                   max_size=None, open_timeout=60) as ws:
                self.connected.set()
                subs: dict[int, str] = {}
                while True:
                    try:
                        msg = ws.recv(timeout=300)
                    except websockets.exceptions.ConnectionClosed:
                        return  # the run ended
                    if isinstance(msg, str):
                        j = json.loads(msg)
                        if j.get("op") != "advertise":
                            continue
                        foxglove_subscribe(ws, j, TYPES, self.channels, subs)
                        continue
                    if msg[0] != 0x01:  # not message data (opcode, subscription id, log time, payload)
                        continue
                    sid, _log_ns = struct.unpack_from("<IQ", msg, 1)
                    self.got[subs[sid]].append(bytes(msg[13:]))
        except BaseException as e:  # said by the test
            self.error = e
            self.connected.set()


@pytest.mark.e2e
@pytest.mark.timeout(300)
def test_the_rover_live_in_rerun_and_over_foxglove_is_the_bag_and_the_truth(tmp_path: Path) -> None:
    from mcap.records import Schema
    from mcap_ros2.decoder import DecoderFactory
    from pyproj import Geod
    from rosbags.typesys import Stores, get_typestore

    started = time.monotonic()
    run, saved = tmp_path / "run", tmp_path / "live.rrd"
    port = transport.free_port()
    p = up(str(SCENARIO), "--view", "--view-wait", "120", "--foxglove", str(port), "--clock", "lockstep",
           "--out", str(run), "--set", f"task.targets=[{list(TARGET)}]")
    assert p.stdout is not None
    lines: list[str] = []
    rest: list[str] = []
    client: subprocess.Popen[bytes] | None = None
    fox = FoxgloveClient(f"ws://127.0.0.1:{port}")
    try:
        for line in p.stdout:  # up to where the run waits for its viewer, physics not started
            lines.append(line)
            if line.startswith("waiting for a viewer"):
                break
        text = "".join(lines)
        assert f"foxglove: ws://127.0.0.1:{port}\n" in text and "viewer: http://127.0.0.1:" in text, text
        reader = threading.Thread(target=lambda: rest.extend(p.stdout), daemon=True)  # type: ignore[arg-type]
        reader.start()
        fox.start()  # the Foxglove client first: it is there when the rover starts
        assert fox.connected.wait(60) and fox.error is None, fox.error
        info = live_viewer.read_live(run)
        assert info is not None, text
        live_viewer.join(info)  # as the page does; then Rerun's client connects, and the run starts
        client = subprocess.Popen([rerun_executable(), "--connect", info["grpc"], "--save", str(saved)],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                  env={**os.environ, **rerun_env()})
        try:  # the reader thread takes what it prints (one reader of the pipe, not two)
            p.wait(240)
        except subprocess.TimeoutExpired:
            raise AssertionError("hilsim up still running after 240 s; it printed:\n" + "".join(lines + rest)) from None
        reader.join(30)
        fox.join(30)  # the server closed with the run
        client.wait(30)  # "Log stream disconnected": it saves and ends with the stream
    finally:
        if p.poll() is None:  # no run left behind by a failure
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(30)
        if client is not None and client.poll() is None:
            client.kill()
            client.wait(30)
    text = "".join(lines + rest)
    assert p.returncode == 0 and "result: OK" in text and "targets reached: 1/1" in text, text[-3000:]
    assert "a viewer joined: starting" in text, text[-3000:]
    assert fox.error is None and not fox.is_alive(), fox.error
    assert not (run / "foxglove.json").exists() and not (run / live.LIVE_NAME).exists()  # both stopped with it
    run_s = time.monotonic() - started

    bag, raw = _bag(run)
    truth: dict[int, Any] = bag["/rover/truth/odom"]
    end = truth[max(truth)].pose.pose.position
    assert math.hypot(end.x - TARGET[0], end.y - TARGET[1]) < GOAL_TOLERANCE, (end, TARGET)

    def xy(t: int) -> tuple[float, float]:
        pos = truth[t].pose.pose.position
        return pos.x, pos.y

    def spread(times: list[int]) -> float:
        """How far apart the truth puts the rover over these sim times [m]: it drove while they were sent."""
        pts = np.array([xy(t) for t in times if t in truth])
        return float(np.ptp(pts, axis=0).max()) if len(pts) else 0.0

    # ---------------------------------------------------------------- Rerun's client: the live stream
    rows = _live_rows(saved)
    # the pose: the chassis' transform in the world, the truth's at the same sim time
    poses = rows.get("/tf/base_link", [])
    for t, r in poses:
        o = truth[t].pose.pose
        assert r["Transform3D:parent_frame"] == ["world"] and r["Transform3D:child_frame"] == ["base_link"], r
        got_p, got_q = r["Transform3D:translation"][0], r["Transform3D:quaternion"][0]
        assert np.abs(np.subtract(got_p, [o.position.x, o.position.y, o.position.z])).max() < F32_M, (t, got_p, o)
        q = o.orientation
        assert np.abs(np.subtract(got_q, [q.x, q.y, q.z, q.w])).max() < F32_Q, (t, got_q, q)
    # thinned to 30 rows a second of sim time (hilsim.record.live_rows); a third of them is plenty
    assert len(poses) > 10 * max(truth) / 1e9 and spread([t for t, _ in poses]) > 5, (len(poses), max(truth))
    # the scan: each row the bag's scan of its sim time, its finite ranges as points in the laser's frame
    scans = rows.get("/scan", [])
    for t, r in scans:
        m = bag["/rover/scan"][t]
        ranges = np.asarray(m.ranges, dtype=float)
        a = m.angle_min + m.angle_increment * np.arange(len(ranges))
        ok = np.isfinite(ranges)
        want = np.column_stack([ranges[ok] * np.cos(a[ok]), ranges[ok] * np.sin(a[ok]), np.zeros(ok.sum())])
        got = np.asarray(r["Points3D:positions"], dtype=float)
        assert r["CoordinateFrame:frame"] == [m.header.frame_id] and got.shape == want.shape, (t, got.shape)
        assert np.abs(got - want).max() < 1e-4, t  # float32 points of ranges under 20 m; the noise is 1e-2
    # all of them at 10 Hz (under the live stream's 30 rows a second) unless frames were dropped for a slow
    # viewer (by design); half of them, spread over the drive, is what is asked
    scan_times, n_scans = sorted({t for t, _ in scans}), len(bag["/rover/scan"])
    assert len(scan_times) >= n_scans / 2 and spread(scan_times) > 5, (len(scan_times), n_scans)
    # the GPS: each row of the track on the map ends with the bag's fix of its sim time
    fixes = rows.get("/geo/gps", [])
    for t, r in fixes:
        m = bag["/rover/gps/fix"][t]
        assert np.allclose(r["GeoPoints:positions"][-1], [m.latitude, m.longitude], rtol=0, atol=1e-9), (t, r)
    fix_times, n_fixes = sorted({t for t, _ in fixes}), len(bag["/rover/gps/fix"])
    assert len(fix_times) >= n_fixes / 2 and spread(fix_times) > 5, (len(fix_times), n_fixes)
    # the map: the bag's occupancy grid of its sim time, a quad its size where it lies, its cells the texture's
    maps = rows.get("/map", [])
    for t, r in maps:
        g = bag["/rover/map"][t]
        w, h, res = g.info.width, g.info.height, g.info.resolution
        fmt = r["Mesh3D:albedo_texture_format"][0]
        assert (fmt["width"], fmt["height"]) == (w, h), (fmt, w, h)
        o = g.info.origin.position
        corners = np.asarray(r["Mesh3D:vertex_positions"], dtype=float)[:, :2]
        assert np.abs(corners.min(axis=0) - [o.x, o.y]).max() < 1e-4, (corners, o)
        assert np.abs(corners.max(axis=0) - [o.x + w * res, o.y + h * res]).max() < 1e-3, (corners, w, h, res)
        texels = np.asarray(r["Mesh3D:albedo_texture_buffer"][0], dtype=np.uint8).reshape(h, w, -1)[..., 0]
        cells = np.asarray(g.data, dtype=np.int16).reshape(h, w)
        occupied, free = texels[cells == 100], texels[cells == 0]
        assert occupied.size and free.size and occupied.max() < free.min(), (occupied.size, free.size)
    assert len({t for t, _ in maps}) >= 2, [t for t, _ in maps]  # the map at its start and as it drove on

    # ---------------------------------------------------------------- the Foxglove client
    ch = fox.channels
    assert {t: ch[t]["schemaName"] for t in TYPES if t in ch} == TYPES, {t: c["schemaName"] for t, c in ch.items()}
    store = get_typestore(Stores.ROS2_JAZZY)
    dec = {}
    for topic, c in ch.items():
        assert c["encoding"] == "cdr" and c["schemaEncoding"] == "ros2msg", c
        schema = Schema(id=1, name=c["schemaName"], encoding="ros2msg", data=c["schema"].encode())
        dec[topic] = DecoderFactory().decoder_for("cdr", schema)
    got: dict[str, list[tuple[Any, Any]]] = {}
    for topic, payloads in fox.got.items():
        for payload in payloads:
            assert payload in raw[topic], f"{topic}: a message the bag does not hold"  # the recorder's bytes
            got.setdefault(topic, []).append((dec[topic](payload), store.deserialize_cdr(payload, TYPES[topic])))
    # (a slow client's oldest may be dropped: hence 90 % of a dense topic)
    for topic in ("/rover/scan", "/rover/odom", "/rover/gps/fix"):
        n, in_bag = len(got.get(topic, [])), len(raw[topic])
        assert n >= 0.9 * in_bag, f"{topic}: {n} of the bag's {in_bag} messages over Foxglove"
    # a channel is advertised with its first sample, before any client could subscribe: the server gives it to
    # one that subscribes before the next; so every map came, the first (and only one for 5 s) included
    assert set(fox.got["/rover/map"]) == raw["/rover/map"], (len(fox.got["/rover/map"]), len(raw["/rover/map"]))

    laser = load_scenario(SCENARIO).sensors["laser"]
    rays = round(laser.fov / laser.resolution) + 1  # ends included (a fov under a full turn)
    for m, other in got["/rover/scan"]:
        assert len(m.ranges) == rays and np.array_equal(np.asarray(other.ranges), np.asarray(m.ranges)), len(m.ranges)
        assert m.angle_min == pytest.approx(-laser.fov / 2, abs=1e-6)  # float32 fields
        assert m.angle_increment == pytest.approx(laser.resolution, abs=1e-7) == other.angle_increment
        assert m.header.frame_id == other.header.frame_id == "laser"
    # /tf: the chassis in the world is the truth of its stamp (both the physics' state of one step), and the
    # antenna's place on the chassis, for the GPS below
    chassis, antenna = 0, None
    for m, other in got["/tf"]:
        assert [(x.header.frame_id, x.child_frame_id) for x in m.transforms] == \
               [(x.header.frame_id, x.child_frame_id) for x in other.transforms]
        for x, y in zip(m.transforms, other.transforms, strict=True):
            a, b = x.transform.translation, y.transform.translation
            assert (a.x, a.y, a.z, _ns(x.header)) == (b.x, b.y, b.z, _ns(y.header))
            if (x.header.frame_id, x.child_frame_id) == ("world", "base_link"):
                o, q = truth[_ns(x.header)].pose.pose, x.transform.rotation
                assert abs(a.x - o.position.x) + abs(a.y - o.position.y) + abs(a.z - o.position.z) < 1e-9, (x, o)
                r_ = o.orientation
                assert max(abs(q.x - r_.x), abs(q.y - r_.y), abs(q.z - r_.z), abs(q.w - r_.w)) < 1e-9, (x, o)
                chassis += 1
            elif (x.header.frame_id, x.child_frame_id) == ("base_link", "gps"):
                antenna = (a.x, a.y, a.z)
    assert chassis >= 0.9 * len(truth) and antenna is not None, (chassis, len(truth), antenna)
    # the odometry (the controller's estimate, frame odom where the rover started) near the truth; the
    # navigator stops by it within 0.1 m of a goal and the truth must be within 0.2 m: its error stays below
    start = truth[min(truth)].pose.pose
    c0, s0 = math.cos(_yaw(start.orientation)), math.sin(_yaw(start.orientation))
    worst = 0.0
    for m, other in got["/rover/odom"]:
        p_, q_ = m.pose.pose.position, other.pose.pose.position
        assert (p_.x, p_.y, m.child_frame_id, m.header.frame_id) == (q_.x, q_.y, other.child_frame_id, "odom")
        tx, ty = xy(_ns(m.header))
        wx, wy = start.position.x + c0 * p_.x - s0 * p_.y, start.position.y + s0 * p_.x + c0 * p_.y
        worst = max(worst, math.hypot(wx - tx, wy - ty))
    assert worst < GOAL_TOLERANCE, worst
    # the GPS: each fix (north and east of the world's geodetic datum, by pyproj's geodesic on WGS 84) is the
    # antenna's true place (the truth's chassis and /tf's chassis -> gps) plus the configured error: σ 1 m on
    # each axis (sensors.gps.horizontal_std); UTM's grid north, the sensor's, is 0.3° off true north here
    # (under 5 cm over the ~10 m driven)
    std = load_scenario(SCENARIO).sensors["gps"].horizontal_std
    numeric = next(n for n in ET.parse(REPO / "models" / "worlds" / "outdoor.xml").iter("numeric")
                   if n.get("name") == "geodetic_datum")
    lat0, lon0, _alt0 = map(float, numeric.get("data", "").split())
    geod, errors = Geod(ellps="WGS84"), []
    for m, other in got["/rover/gps/fix"]:
        assert (m.latitude, m.longitude, m.altitude) == (other.latitude, other.longitude, other.altitude)
        az, _, d = geod.inv(lon0, lat0, m.longitude, m.latitude)
        o = truth[_ns(m.header)].pose.pose
        place = np.array([o.position.x, o.position.y, o.position.z]) + _rotate(o.orientation, antenna)
        errors.append((d * math.cos(math.radians(az)) - place[0], d * math.sin(math.radians(az)) - place[1]))
    e = np.asarray(errors)
    rms, mean = np.sqrt((e**2).mean(axis=0)), e.mean(axis=0)
    # with n fixes: no error past 5σ, a mean within 4σ/√n of none, an RMS that is σ's (not 0: not the truth
    # itself; not more: not another place)
    assert np.hypot(e[:, 0], e[:, 1]).max() < 5 * std, e
    assert np.abs(mean).max() < 4 * std / math.sqrt(len(e)), mean
    assert (0.5 * std < rms).all() and (rms < 1.5 * std).all(), rms
    # the map over Foxglove: the bag's grid, decoded the same both ways
    for m, other in got["/rover/map"]:
        assert (m.info.width, m.info.height) == (other.info.width, other.info.height)
        assert np.array_equal(np.asarray(m.data), np.asarray(other.data))
    assert got["/rover/map"], "no map over Foxglove"
    print(f"live rover: the run {run_s:.0f} s; Rerun's client got {len(poses)} poses (the truth's to {F32_M} m), "
          f"{len(scan_times)} scans, {len(fix_times)} GPS fixes and {len(maps)} maps of the bag's "
          f"{len(bag['/rover/scan'])}/{len(bag['/rover/gps/fix'])}/{len(bag['/rover/map'])}; Foxglove: "
          f"{ {t: len(v) for t, v in fox.got.items()} }, {chassis} chassis transforms the truth's, odometry within "
          f"{worst:.3f} m of it, GPS error RMS {rms.round(2).tolist()} m, mean {mean.round(2).tolist()} m")
