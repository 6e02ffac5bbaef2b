"""CAN hardware in the loop, in one process: the ODrive CAN Simple frames (DBC, byte layout, bad
frames), the joint <-> motor mapping, and the CAN bridge against the drive emulator on python-can's
``virtual`` bus (both services in threads, real Zenoh): commands out, state back, and the faults
(heartbeat loss, axis error, garbage frames, a bus missing at start, bus-off, a drive that comes
back, the other drives held)."""

from __future__ import annotations

import itertools
import math
import random
import struct
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import pytest
import zenoh

from hilsim.bridges import can_bus
from hilsim.bridges.can_bridge import CanBridgeService
from hilsim.bridges.can_bus import BusConfig, JointMap
from hilsim.bridges.can_profiles import DriveCommand, Estimate, FrameError, Heartbeat, make_profile, struct_layout
from hilsim.bridges.drive_emulator import DriveEmulatorService
from hilsim.core import msgs, transport
from hilsim.core.config import ConfigError, ZenohConfig
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario

REPO = Path(__file__).resolve().parent.parent
CAN_HIL = REPO / "config" / "hil" / "can.yaml"
_channels = itertools.count()


# ------------------------------------------------------------------ protocol
def test_odrive_frames_have_the_documented_layout() -> None:
    p = make_profile("odrive")
    f = p.command_frame(3, "position", 2 * math.pi * 1.25, 2 * math.pi * 0.5, -0.002)
    assert f.arbitration_id == 3 << 5 | 0x0C and not f.is_extended_id
    assert bytes(f.data) == struct.pack("<fhh", 1.25, 500, -2)
    f = p.command_frame(1, "velocity", 0.0, 2 * math.pi * -2.0, 0.0)
    assert f.arbitration_id == 0x2D and bytes(f.data) == struct.pack("<ff", -2.0, 0.0)
    f = p.command_frame(0, "effort", 0.0, 0.0, 0.75)
    assert f.arbitration_id == 0x0E and bytes(f.data) == struct.pack("<f", 0.75)
    modes = [bytes(p.mode_frame(0, i).data) for i in ("effort", "velocity", "position")]
    assert modes == [struct.pack("<ii", m, 1) for m in (1, 2, 3)]
    assert bytes(p.state_frame(2, 8).data) == struct.pack("<I", 8) and p.state_frame(2, 8).arbitration_id == 0x47
    hb = p.heartbeat_frame(Heartbeat(5, 0x200, 8, 0, True))
    assert hb.arbitration_id == 5 << 5 | 1 and bytes(hb.data) == struct.pack("<IBBBx", 0x200, 8, 0, 1)
    est = p.estimate_frame(Estimate(0, 2 * math.pi * 0.25, 2 * math.pi * -1.5))
    assert est.arbitration_id == 9 and bytes(est.data) == struct.pack("<ff", 0.25, -1.5)
    rtr = p.estimate_request(4)
    assert rtr.is_remote_frame and rtr.arbitration_id == 4 << 5 | 9
    # and back
    assert p.parse(hb) == Heartbeat(5, 0x200, 8, 0, True)
    e = p.parse(est)
    assert isinstance(e, Estimate) and e.position == pytest.approx(math.pi / 2)
    assert e.velocity == pytest.approx(-3 * math.pi)
    assert p.parse(rtr) == DriveCommand(4, "request_estimate")
    c = p.parse(p.command_frame(3, "position", 1.0, 2.0, 0.5))
    assert c.kind == "position" and c.a == pytest.approx(1.0, abs=1e-6) and c.b == pytest.approx(2.0, abs=0.01)
    assert p.direction(hb) == "to_host" and p.direction(rtr) == "to_drive" and p.direction(f) == "to_drive"


@pytest.mark.parametrize(("frame", "kind"), [
    (can.Message(arbitration_id=0x1F, data=b"\0" * 8, is_extended_id=False), "unknown_id"),
    (can.Message(arbitration_id=0x12345, data=b"\0" * 8, is_extended_id=True), "unknown_id"),
    (can.Message(arbitration_id=0x01, data=b"\0" * 3, is_extended_id=False), "bad_length"),
    (can.Message(arbitration_id=0x09, data=struct.pack("<ff", math.nan, 0.0), is_extended_id=False), "malformed"),
    (can.Message(arbitration_id=0x21, is_remote_frame=True, dlc=8, is_extended_id=False), "unknown_id"),
])
def test_frames_of_no_use_say_why(frame: can.Message, kind: str) -> None:
    with pytest.raises(FrameError) as e:
        make_profile("odrive").parse(frame)
    assert e.value.kind == kind


def test_joint_mapping_and_profile_lookup() -> None:
    m = JointMap(node_id=0, gear_ratio=9.0, direction=-1, offset=0.2)
    assert m.to_motor(0.2) == 0.0 and m.to_joint(m.to_motor(0.7)) == pytest.approx(0.7)
    assert m.to_motor(0.3) == pytest.approx(-0.9) and m.vel_to_motor(1.0) == -9.0
    assert m.torque_to_motor(9.0) == -1.0 and m.torque_to_joint(-1.0) == pytest.approx(9.0)
    with pytest.raises(ConfigError, match=r"unknown CAN profile 'cia402'; available: odrive"):
        make_profile("cia402")


def test_the_bridge_config_names_every_joint_it_serves(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("joints: {joint_2: {interface: velocity, server: bridge-can}}\n")
    sc = load_scenario("arm", overlays=[CAN_HIL, bad])
    with pytest.raises(ConfigError, match=r"bridge-can\.joints: no drive given for joint_2"):
        CanBridgeService(sc)


# ------------------------------------------------------------------ bridge <-> emulated drives
class Rig:
    """The bridge and the emulator (model mode) on one virtual bus, a Zenoh session of the test."""

    def __init__(self, router: str, run_service: Callable[[Any], Any], extra: dict[str, Any]) -> None:
        channel = f"hilsim-test-{next(_channels)}-{time.monotonic_ns()}"
        o = {
            "zenoh.connect": [router],
            "joints.joint_2": {"interface": "velocity", "server": "bridge-can"},
            "bridge-can.bus": {"interface": "virtual", "channel": channel},
            "bridge-can.joints.joint_1": {"node_id": 0, "gear_ratio": 2.0, "direction": -1, "offset": 0.1},
            "bridge-can.joints.joint_2": {"node_id": 1},
            "bridge-can.heartbeat_period": 0.05,
            "bridge-can.recover_interval": 0.1,
            "bridge-can.reconnect_interval": 0.2,
            "drive-emulator.heartbeat_period": 0.05,
            "drive-emulator.encoder_period": 0.005,
            "drive-emulator.initial_position": {"joint_1": 0.1},
            # both in this process: no real-time scheduling class for the test's threads
            "bridge-can.realtime_priority": 0,
            "drive-emulator.realtime_priority": 0,
        }
        o.update(extra)
        self.sc = load_scenario("arm", o, overlays=[CAN_HIL])
        self.channel = channel
        self.keys = Keys(self.sc.prefix, self.sc.robot)
        self.session = transport.open_session(ZenohConfig(connect=[router]))
        self.lock = threading.Lock()
        self.logs: list[tuple[int, str]] = []
        self.states: list[msgs.JointState] = []
        s = self.session
        self.subs = [
            s.declare_subscriber(self.keys.log("bridge-can"), self._on_log),
            s.declare_subscriber(self.keys.server_state("bridge-can"), self._on_state),
        ]
        self.cmd = s.declare_publisher(self.keys.topic("joint_commands"))
        self.bridge = CanBridgeService(self.sc)
        self.emulator = DriveEmulatorService(self.sc)
        self.run_service = run_service
        self.ctx: list[Any] = []

    def _on_log(self, sample: zenoh.Sample) -> None:
        m = msgs.decode(msgs.Log, sample.payload.to_bytes())
        with self.lock:
            self.logs.append((m.level, m.msg))

    def _on_state(self, sample: zenoh.Sample) -> None:
        m = msgs.decode(msgs.JointState, sample.payload.to_bytes())
        with self.lock:
            self.states.append(m)

    def start(self, *services: Any) -> None:
        for svc in services:
            cm = self.run_service(svc)
            cm.__enter__()
            self.ctx.append(cm)

    def close(self) -> None:
        for cm in reversed(self.ctx):
            cm.__exit__(None, None, None)
        for s in self.subs:
            s.undeclare()
        self.cmd.undeclare()
        self.session.close()

    def command(self, joint_1: float, joint_2: float) -> None:
        """joint_1 (position interface) to a position, joint_2 (velocity) at a velocity."""
        self.cmd.put(msgs.encode(msgs.JointState(header=msgs.header(0), name=["joint_1", "joint_2"],
                                                 position=[joint_1, 0.0], velocity=[0.0, joint_2], effort=[0.0, 0.0])))

    def drive(self, node: int) -> Any:
        return self.emulator.drives[node]

    def joint(self, name: str) -> Any:
        return self.bridge.joints[name]

    def said(self, level: int, text: str) -> bool:
        with self.lock:
            return any(lv == level and text in m for lv, m in self.logs)

    def measured(self, name: str) -> float | None:
        with self.lock:
            for m in reversed(self.states):
                if name in m.name:
                    return m.position[m.name.index(name)]
        return None


def wait_for(cond: Callable[[], Any], timeout: float = 5.0, what: str | Callable[[], str] = "") -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {(what() if callable(what) else what) or cond}")
        time.sleep(0.01)


@pytest.fixture
def rig(router: str, run_service: Callable[[Any], Any]) -> Iterator[Callable[..., Rig]]:
    made: list[Rig] = []

    def make(**extra: Any) -> Rig:
        r = Rig(router, run_service, extra)
        made.append(r)
        return r

    yield make
    for r in made:
        r.close()


def test_commands_reach_the_drive_and_its_state_comes_back_in_joint_units(rig: Callable[..., Rig]) -> None:
    r = rig()
    r.start(r.emulator, r.bridge)
    wait_for(lambda: r.joint("joint_1").status == "ok" and r.joint("joint_2").status == "ok", what="closed loop")
    d1, d2 = r.drive(0), r.drive(1)
    assert d1.closed_loop and d1.mode == "position" and d2.mode == "velocity"
    assert r.bridge.state == "running"
    # joint_1: gear 2, direction -1, offset 0.1 -> motor = -2 (q - 0.1)
    for _ in range(150):
        r.command(joint_1=0.4, joint_2=0.5)
        time.sleep(0.01)
    assert d1.p == pytest.approx(-0.6, abs=0.01)  # the drive's motor, in motor rad
    assert d2.v == pytest.approx(0.5, abs=0.02)  # velocity mode: 0.5 rad/s
    wait_for(lambda: abs((r.measured("joint_1") or 0) - 0.4) < 0.01, what="joint_1 measured at 0.4 rad")
    assert r.bridge.health_values()["frames_malformed"] == 0


def test_heartbeat_loss_is_a_fault_the_other_drive_is_held_and_both_come_back(rig: Callable[..., Rig]) -> None:
    r = rig()
    r.start(r.emulator, r.bridge)
    wait_for(lambda: r.joint("joint_1").status == "ok" and r.joint("joint_2").status == "ok", what="closed loop")
    r.drive(1).silent = True  # joint_2's drive stops talking
    wait_for(lambda: r.said(40, "joint_2 (node 1): heartbeat lost"), what="heartbeat fault")
    assert r.bridge.state == "fault" and r.joint("joint_2").status == "fault"
    assert r.bridge.health().status[0].level == 2
    # joint_1 held where it is: position mode, and commands no longer reach it
    wait_for(lambda: r.joint("joint_1").held, what="joint_1 held")
    hold = r.drive(0).inputs[0]
    for _ in range(20):
        r.command(joint_1=1.0, joint_2=0.3)
        time.sleep(0.01)
    assert r.drive(0).inputs[0] == hold and r.drive(0).mode == "position"
    assert r.drive(1).inputs[1] == 0.0  # the silent drive got no setpoint either
    r.drive(1).silent = False
    wait_for(lambda: r.said(20, "joint_2 (node 1) recovered (heartbeat lost"), what="recovery said")
    wait_for(lambda: r.said(20, "joint_1 (node 0) released"), what="release said")
    assert r.bridge.state == "running"
    r.command(joint_1=0.35, joint_2=0.3)
    wait_for(lambda: r.drive(1).inputs[1] == pytest.approx(0.3, abs=1e-6), what="joint_2 follows again")


def test_an_axis_error_is_a_fault_cleared_by_the_bridge(rig: Callable[..., Rig]) -> None:
    r = rig()
    r.start(r.emulator, r.bridge)
    wait_for(lambda: r.joint("joint_1").status == "ok", what="closed loop")
    d = r.drive(0)
    with r.emulator.lock:
        d.fail(0x200, sticky=True)  # a drive error that does not go away by itself
    wait_for(lambda: r.said(40, "joint_1 (node 0): axis error 0x200"), what="axis error fault")
    n = d.commands
    time.sleep(0.5)
    assert r.joint("joint_1").status == "fault" and d.commands > n  # it keeps trying to clear it
    assert d.state == d.profile.IDLE
    with r.emulator.lock:
        d.sticky_error = False  # now Clear_Errors works
    wait_for(lambda: r.said(20, "joint_1 (node 0) recovered (axis error 0x200"), what="recovery")
    assert d.closed_loop and d.error == 0


def test_garbage_frames_are_counted_not_fatal(rig: Callable[..., Rig]) -> None:
    r = rig()
    r.start(r.emulator, r.bridge)
    wait_for(lambda: r.joint("joint_1").status == "ok", what="closed loop")
    bus = can.Bus(interface="virtual", channel=r.channel)
    try:
        junk = [
            can.Message(arbitration_id=0x1F, data=b"\xff" * 8, is_extended_id=False),  # unknown command
            can.Message(arbitration_id=0x01, data=b"\x00\x01", is_extended_id=False),  # short heartbeat
            can.Message(arbitration_id=0x09, data=struct.pack("<ff", math.inf, 0.0), is_extended_id=False),
            can.Message(arbitration_id=0x1ABCDEF, data=b"\x00", is_extended_id=True),  # not CAN Simple
            can.Message(arbitration_id=0x3E9, data=b"\x00" * 8, is_extended_id=False),  # node 31 heartbeat
        ]
        for _ in range(3):
            for f in junk:
                bus.send(f)
    finally:
        bus.shutdown()
    wait_for(lambda: r.bridge.bad["malformed"] == 3 and r.bridge.bad["bad_length"] == 3, what="counted")
    h = r.bridge.health_values()
    assert (h["frames_unknown_id"], h["frames_bad_length"], h["frames_malformed"]) == (6, 3, 3)
    assert h["frames_other_nodes"] >= 3
    assert r.bridge.state == "running" and r.joint("joint_1").status == "ok"
    wait_for(lambda: r.said(30, "CAN frame not used (malformed"), what="the warning")
    assert r.emulator.bad["unknown_id"] >= 6  # the drives count them too


def test_a_bus_missing_at_start_then_bus_off_faults_and_recovers(rig: Callable[..., Rig],
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    r = rig(**{"bridge-can.open_timeout": 5.0})  # a USB adapter plugged in after the start is waited for
    tries = {"n": 0}
    plugged = threading.Event()  # the test plugs the adapter in once it has seen the fault
    real_open = can_bus.open_bus

    def flaky(cfg: BusConfig) -> can.BusABC:
        tries["n"] += 1
        if not plugged.is_set():  # not there yet, as a USB adapter about to be plugged in
            return can_bus.open_bus(BusConfig(interface="socketcan", channel="hilsimnone0"))
        return real_open(cfg)

    r.bridge.link.opener = flaky
    r.start(r.emulator, r.bridge)
    wait_for(lambda: r.said(40, "CAN bus virtual:"), what="bus fault")
    assert r.said(40, "not available") and r.bridge.state == "fault"
    wait_for(lambda: tries["n"] >= 2, what="a retry while the bus is missing")
    assert r.bridge.state == "fault"
    plugged.set()
    wait_for(lambda: r.said(20, "joint_1 (node 0) recovered (CAN bus down"), timeout=8, what="recovery after bus up")
    assert r.said(20, "up again")
    # the controller goes bus-off: SocketCAN reports it with an error frame
    bus = can.Bus(interface="virtual", channel=r.channel)
    try:
        bus.send(can.Message(arbitration_id=can_bus.CAN_ERR_BUSOFF, is_error_frame=True, dlc=8, data=bytes(8)))
    finally:
        bus.shutdown()
    wait_for(lambda: r.said(40, "bus-off"), what="bus-off fault")
    assert r.bridge.link.outages == 2
    wait_for(lambda: r.bridge.state == "running" and r.joint("joint_1").status == "ok", timeout=8,
             what="running after bus-off")


def test_a_bus_that_cannot_open_at_start_stops_the_bridge_with_the_reason(rig: Callable[..., Rig],
                                                                          caplog: pytest.LogCaptureFixture) -> None:
    """No adapter at start (open_timeout 0, the default): the bridge exits non-zero at once, its
    reason in one line (hilsim up then ends the run), instead of a fault the planner finds later."""
    r = rig(**{"bridge-can.bus": {"interface": "socketcan", "channel": "hilsimnone0"}})
    r.start(r.bridge)
    t = r.ctx[-1]
    t.thread.join(5)
    assert not t.thread.is_alive() and t.rc == 1 and r.bridge.state == "fault"
    assert r.bridge.link.handle is None and not r.bridge.link.opened_once
    assert "stopped: CAN bus socketcan:hilsimnone0 not available: " in caplog.text, caplog.text


def test_without_ipv6_multicast_both_ends_take_the_ipv4_group(monkeypatch: pytest.MonkeyPatch,
                                                               caplog: pytest.LogCaptureFixture) -> None:
    """python-can's default IPv6 group where IPv6 multicast cannot be joined (forced here; a netns
    without IPv6 in tests/test_can_e2e.py): the bridge and the drive emulator, each deciding on its
    own from the same scenario, both take python-can's IPv4 group on the same port, and say so; a
    group the scenario chose is never changed; a udp_multicast bus that does not open says what to do."""
    demo = REPO / "config" / "hil" / "can-emulated.yaml"
    monkeypatch.setattr(can_bus, "_ipv6_probe", "No such device")
    sc = load_scenario("arm", {"bridge-can.bus.port": 43999}, overlays=[demo])
    bridge, emulator = CanBridgeService(sc), DriveEmulatorService(sc)
    assert bridge.cfg.bus.kwargs() == emulator.bus_cfg.kwargs() == {
        "interface": "udp_multicast", "channel": can_bus.UDP_GROUP_IPV4, "port": 43999}
    assert caplog.text.count("IPv6 multicast is not available on this host (No such device)") == 2
    chosen = load_scenario("arm", {"bridge-can.bus.channel": "ff15::4242"}, overlays=[demo])
    assert CanBridgeService(chosen).cfg.bus.channel == "ff15::4242"
    monkeypatch.setattr(can_bus, "_ipv6_probe", "")  # a host with IPv6 multicast: as configured
    assert CanBridgeService(sc).cfg.bus.channel == can_bus.UDP_GROUP_IPV6

    def no_socket(**kw: Any) -> can.BusABC:
        try:
            raise OSError(19, "No such device")
        except OSError as e:
            raise can.CanInitializationError("could not create or configure socket") from e

    monkeypatch.setattr(can, "Bus", no_socket)
    monkeypatch.setattr(can_bus, "_ipv6_probe", "No such device")
    with pytest.raises(ConnectionError) as v4:
        can_bus.open_bus(BusConfig(channel=can_bus.UDP_GROUP_IPV4, port=43999))
    assert "could not create or configure socket (No such device)" in str(v4.value)
    assert "ip route add 224.0.0.0/4 dev lo" in str(v4.value) and "no IPv6 multicast either" in str(v4.value)
    with pytest.raises(ConnectionError) as v6:
        can_bus.open_bus(BusConfig(channel="ff15::4242"))
    assert f"--set bridge-can.bus.channel={can_bus.UDP_GROUP_IPV4}" in str(v6.value)


def test_nothing_on_the_bus_is_a_fault_not_a_hang(rig: Callable[..., Rig]) -> None:
    r = rig()
    r.start(r.bridge)  # no drive at all
    wait_for(lambda: r.said(40, "joint_1 (node 0): no heartbeat from node 0"), what="no-drive fault")
    # the two faults are said one after the other: wait for the second too, do not race it
    wait_for(lambda: r.said(40, "joint_2 (node 1): no heartbeat from node 1"), what="the second no-drive fault")
    assert r.measured("joint_1") is None


# ------------------------------------------------------------------ the state path under load
def test_the_encoder_fast_path_decodes_exactly_like_cantools(tmp_path: Path) -> None:
    """The struct the profile lays out from the DBC gives what cantools gives, for random frames of
    every message that has one, and ``parse`` of the cyclic encoder estimate uses it; a DBC whose
    encoder layout has no struct equivalent (scaled) is decoded by cantools, by its own scale."""
    rng = random.Random(8)
    p = make_profile("odrive")
    assert p.encoder_struct is not None  # the fast path is on for the shipped DBC
    laid_out = 0
    for m in p.db.messages:
        layout = struct_layout(m)
        if layout is None:
            continue
        laid_out += 1
        st, names = layout
        assert st.size == m.length and set(names) == {s.name for s in m.signals}
        for _ in range(300):
            data = rng.randbytes(m.length)
            ref = m.decode(data, decode_choices=False)
            got = dict(zip(names, st.unpack(data), strict=True))
            for n in names:
                assert got[n] == ref[n] or (math.isnan(got[n]) and math.isnan(ref[n])), (m.name, data, n)
    assert laid_out >= 5
    enc = p.by_cmd[p.ENCODER]
    specials = [struct.pack("<ff", x, y) for x, y in ((0.0, -0.0), (1e-45, -3.4e38), (math.inf, 0.0),
                                                       (0.0, math.nan), (123.456, -7.5))]
    for data in specials + [rng.randbytes(8) for _ in range(2000)]:
        f = can.Message(arbitration_id=5 << 5 | 0x09, data=data, is_extended_id=False)
        ref = enc.decode(data, decode_choices=False)
        if all(math.isfinite(v) for v in ref.values()):
            assert p.parse(f) == Estimate(5, ref["Pos_Estimate"] * 2 * math.pi, ref["Vel_Estimate"] * 2 * math.pi)
        else:
            with pytest.raises(FrameError) as e:
                p.parse(f)
            assert e.value.kind == "malformed"
    # the DBC stays the truth: a scaled encoder position has no struct, cantools applies the scale
    dbc = tmp_path / "scaled.dbc"
    text = (REPO / "config" / "can" / "odrive-cansimple.dbc").read_text()
    assert " SG_ Pos_Estimate : 0|32@1- (1,0)" in text
    dbc.write_text(text.replace(" SG_ Pos_Estimate : 0|32@1- (1,0)", " SG_ Pos_Estimate : 0|32@1- (0.5,0)"))
    scaled = make_profile("odrive", dbc)
    assert scaled.encoder_struct is None
    e = scaled.parse(can.Message(arbitration_id=0x09, data=struct.pack("<ff", 3.0, 1.0), is_extended_id=False))
    assert isinstance(e, Estimate) and e.position == pytest.approx(1.5 * 2 * math.pi)


def _burst(r: Rig, n: int) -> list[float]:
    """``n`` encoder estimates of node 0 (joint_1), sent back to back while the bridge's reader is
    held (it waits for the bridge's lock on the first one), so the rest queue up on the bus
    together; the joint positions they stand for, in order. Before: one estimate that must come
    through (the bridge's publisher has met the test's subscriber); the rig's states and the
    bridge's counters start from zero after it."""
    jm, p, b = r.bridge.joints["joint_1"].map, r.bridge.profile, r.bridge
    frames = [p.estimate_frame(Estimate(0, 0.001 * (k + 1), -0.001 * k)) for k in range(n)]
    bus = can.Bus(interface="virtual", channel=r.channel)
    try:
        wait_for(lambda: b.link.up, what="bus up")
        deadline = time.monotonic() + 10
        while not r.states:
            assert time.monotonic() < deadline, "no state sample on Zenoh"
            bus.send(p.estimate_frame(Estimate(0, -1.0, 0.0)))
            time.sleep(0.1)
        time.sleep(0.2)
        with b.lock, r.lock:
            r.states.clear()
            b.estimates = b.coalesced = b.state_samples = 0
        with b.lock:
            for f in frames:
                bus.send(f)
    finally:
        bus.shutdown()
    return [jm.to_joint(e.position) for e in map(p.parse, frames) if isinstance(e, Estimate)]


def test_a_burst_of_estimates_is_all_absorbed_and_the_newest_state_published(rig: Callable[..., Rig]) -> None:
    """A burst the bridge cannot publish frame by frame: every estimate is taken in (counted, none
    lost), the samples on Zenoh only ever move forward, the last one is the last frame's state,
    and what was not published on its own is counted as coalesced."""
    r = rig(**{"bridge-can.batch_window": 0.005})
    r.start(r.bridge)  # no drive: the test is the drive
    n = 3000
    want = _burst(r, n)
    b = r.bridge
    index = {round(q, 9): k for k, q in enumerate(want)}

    def seen() -> list[int]:
        """Which burst frame each sample received reflects (a late warm-up sample is none)."""
        with r.lock:
            qs = [round(m.position[0], 9) for m in r.states if m.name == ["joint_1"]]
        return [index[q] for q in qs if q in index]

    # absorbed, and the last batch published (every estimate either published or coalesced)
    wait_for(lambda: b.estimates == n and b.coalesced + b.state_samples == n, what=f"{n} estimates absorbed")
    wait_for(lambda: len(seen()) == b.state_samples,
             what=lambda: f"every published sample received ({len(seen())} of {b.state_samples})")
    h = b.health_values()
    assert h["estimates"] == n and h["estimates_coalesced"] + h["state_samples"] == n
    assert 0 < h["state_samples"] < n / 5, h  # batched: far fewer samples than frames
    ks = seen()
    assert ks == sorted(set(ks)), "a sample went back to an older frame"
    assert ks[-1] == n - 1
    assert b.joints["joint_1"].pos == pytest.approx(want[-1], abs=1e-9)


def test_with_no_batch_window_each_estimate_is_its_own_sample(rig: Callable[..., Rig]) -> None:
    r = rig(**{"bridge-can.batch_window": 0.0})
    r.start(r.bridge)
    want = _burst(r, 300)
    b = r.bridge
    wait_for(lambda: b.estimates == 300 and b.state_samples == 300, what="300 samples published")
    assert b.coalesced == 0
    time.sleep(0.3)
    # what reached the test (a realtime publisher may drop a burst's sample) came in frame order
    index = {round(q, 9): k for k, q in enumerate(want)}
    with r.lock:
        ks = [index[q] for q in (round(m.position[0], 9) for m in r.states) if q in index]
    assert ks == sorted(set(ks)) and len(ks) >= 30, ks


def test_a_bigger_receive_buffer_keeps_a_burst_the_reader_was_late_for() -> None:
    """A burst that arrives while nobody reads (the process not scheduled): with the bridge's
    receive buffer every frame waits on the socket; with the system's default, the kernel drops
    what does not fit (udp_multicast: ~256 frames)."""
    rmem_max = int(Path("/proc/sys/net/core/rmem_max").read_text())
    if rmem_max < 1 << 20:
        pytest.skip(f"net.core.rmem_max is {rmem_max}: the kernel caps the buffer below 1 MiB")
    port = random.SystemRandom().randint(20000, 60000)
    cfg = BusConfig(interface="udp_multicast", port=port)
    tx, small, big = can_bus.open_bus(cfg), can_bus.open_bus(cfg), can_bus.open_bus(cfg)
    try:
        granted = can_bus.grow_rx_buffer(big, 1 << 20)
        assert granted is not None and granted >= 1 << 20
        v = can.Bus(interface="virtual", channel=f"hilsim-test-{next(_channels)}")
        assert can_bus.grow_rx_buffer(v, 1 << 20) is None  # no socket: nothing to grow, no error
        v.shutdown()
        p = make_profile("odrive")
        n = 1500
        for k in range(n):
            tx.send(p.estimate_frame(Estimate(0, 0.001 * k, 0.0)))
        time.sleep(0.2)

        def drain(bus: can.BusABC) -> int:
            got = 0
            while bus.recv(0) is not None:
                got += 1
            return got

        assert drain(big) == n
        if int(Path("/proc/sys/net/core/rmem_default").read_text()) <= 256 * 1024:
            assert drain(small) < n  # the usual default buffer: the kernel dropped part of the burst
    finally:
        for b in (tx, small, big):
            b.shutdown()
