"""CAN drive protocols ("profiles"): frames <-> drive events, one class per protocol, found by name.

A profile turns python-can frames into drive-neutral events and back. It works in the units of
the *motor shaft* (rad, rad/s, N·m); the joint mapping (gear ratio, direction, offset) is the
bridge's business, the wire units (turns, counts, …) the profile's. Two sides use it:

- the host side (:mod:`hilsim.bridges.can_bridge`): :meth:`DriveProfile.setup_frames`,
  :meth:`~DriveProfile.command_frame`, … to send, :meth:`~DriveProfile.parse` to read the
  drive's :class:`Heartbeat` and :class:`Estimate`;
- the drive side (:mod:`hilsim.bridges.drive_emulator`): :meth:`~DriveProfile.parse` gives the
  host's :class:`DriveCommand`, :meth:`~DriveProfile.heartbeat_frame` and
  :meth:`~DriveProfile.estimate_frame` answer.

Profiles are picked by name (``profile: odrive``): the built-in :data:`PROFILES`, then the
entry-point group ``hilsim.can_profiles`` (``name = "pkg.module:Class"``), so a CANopen CiA 402
profile can be added by another package without changing this file.

A frame that cannot be understood raises :class:`FrameError` with a ``kind``
(``unknown_id``, ``bad_length``, ``malformed``): the caller counts it and goes on.
"""

from __future__ import annotations

import importlib
import math
import struct
from abc import ABC, abstractmethod
from dataclasses import dataclass
from functools import cache
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, ClassVar

import can
import cantools

from hilsim.core.config import CONFIG_DIR, ConfigError

TAU = 2.0 * math.pi
GROUP = "hilsim.can_profiles"
PROFILES: dict[str, str] = {"odrive": "hilsim.bridges.can_profiles:OdriveCanSimple"}


class FrameError(ValueError):
    """A frame of no use: ``kind`` is ``unknown_id``, ``bad_length`` or ``malformed``."""

    def __init__(self, kind: str, text: str) -> None:
        super().__init__(text)
        self.kind = kind


@dataclass(frozen=True, slots=True)
class Heartbeat:
    """A drive's periodic status (drive -> host)."""

    node: int
    error: int
    state: int
    procedure_result: int = 0
    trajectory_done: bool = False


@dataclass(frozen=True, slots=True)
class Estimate:
    """Encoder estimate of a drive (drive -> host): motor shaft position [rad] and velocity [rad/s]."""

    node: int
    position: float
    velocity: float


@dataclass(frozen=True, slots=True)
class DriveCommand:
    """What a host asks of a drive (host -> drive). ``kind``: ``state`` (a = requested state),
    ``mode`` (a = control mode, b = input mode), ``position`` (a = position [rad], b = velocity
    feed-forward [rad/s], c = torque feed-forward [N·m]), ``velocity`` (a = velocity, c = torque
    feed-forward), ``torque`` (c = torque), ``clear_errors``, ``request_estimate`` (an RTR)."""

    node: int
    kind: str
    a: float = 0.0
    b: float = 0.0
    c: float = 0.0


class DriveProfile(ABC):
    """One CAN drive protocol. Units at this interface: motor shaft rad, rad/s, N·m."""

    name: ClassVar[str]
    CLOSED_LOOP: ClassVar[int]  # the axis state in which the drive follows its inputs
    IDLE: ClassVar[int]
    # command interface of a joint -> the drive's control mode
    CONTROL_MODES: ClassVar[dict[str, int]]
    max_node: ClassVar[int] = 63

    def interface_of(self, control_mode: int) -> str | None:
        return next((i for i, m in self.CONTROL_MODES.items() if m == control_mode), None)

    # ---------------------------------------------------------------- host -> drive
    @abstractmethod
    def setup_frames(self, node: int, interface: str, hold: float | None) -> list[can.Message]:
        """Put the drive in the control mode of ``interface`` and into closed-loop control,
        holding ``hold`` [rad] (position mode; its current position when None)."""

    @abstractmethod
    def mode_frame(self, node: int, interface: str) -> can.Message:
        """Set the control mode of ``interface``."""

    @abstractmethod
    def state_frame(self, node: int, state: int) -> can.Message:
        """Request an axis state (e.g. :attr:`IDLE`)."""

    @abstractmethod
    def clear_errors_frame(self, node: int) -> can.Message: ...

    @abstractmethod
    def command_frame(self, node: int, interface: str, position: float, velocity: float,
                      torque: float) -> can.Message:
        """The setpoint of ``interface`` (position with velocity feed-forward, velocity, or torque)."""

    @abstractmethod
    def estimate_request(self, node: int) -> can.Message: ...

    # ---------------------------------------------------------------- drive -> host
    @abstractmethod
    def heartbeat_frame(self, hb: Heartbeat) -> can.Message: ...

    @abstractmethod
    def estimate_frame(self, est: Estimate) -> can.Message: ...

    # ---------------------------------------------------------------- both
    @abstractmethod
    def direction(self, msg: can.Message) -> str | None:
        """A cheap look at the id, no decoding: ``to_drive`` (a host's frame), ``to_host`` (a
        drive's), None (not this protocol's: :meth:`parse` says why)."""

    @abstractmethod
    def parse(self, msg: can.Message) -> Heartbeat | Estimate | DriveCommand:
        """The event a frame carries; :class:`FrameError` if it is none of this protocol's."""


class OdriveCanSimple(DriveProfile):
    """ODrive "CAN Simple": 11-bit id = node_id << 5 | cmd_id, little-endian, frames described in
    ``config/can/odrive-cansimple.dbc`` and encoded/decoded with cantools. Wire units: turns,
    turns/s, N·m."""

    name = "odrive"
    IDLE = 1
    CLOSED_LOOP = 8
    CONTROL_MODES: ClassVar[dict[str, int]] = {"effort": 1, "velocity": 2, "position": 3}
    INPUT_PASSTHROUGH = 1
    HEARTBEAT, SET_AXIS_STATE, ENCODER, SET_MODE = 0x01, 0x07, 0x09, 0x0B
    INPUT_POS, INPUT_VEL, INPUT_TORQUE, CLEAR_ERRORS = 0x0C, 0x0D, 0x0E, 0x18
    FF_LIMIT = 32.767  # the i16 × 0.001 feed-forward fields

    def __init__(self, dbc: Path | None = None) -> None:
        path = dbc or CONFIG_DIR / "can" / "odrive-cansimple.dbc"
        try:
            self.db = cantools.database.load_file(str(path))
        except (OSError, cantools.database.errors.Error) as e:
            raise ConfigError(f"{path}: cannot load the DBC file: {e}") from None
        self.by_cmd = {m.frame_id: m for m in self.db.messages}
        for cmd in (self.HEARTBEAT, self.SET_AXIS_STATE, self.ENCODER, self.SET_MODE, self.INPUT_POS,
                    self.INPUT_VEL, self.INPUT_TORQUE, self.CLEAR_ERRORS):
            if cmd not in self.by_cmd:
                raise ConfigError(f"{path}: no message with id 0x{cmd:02X} (ODrive CAN Simple)")
        # the cyclic encoder estimate is most of a busy bus: decoded by a struct laid out from the
        # DBC's own signals (None: the DBC's layout has no struct equivalent, cantools decodes it)
        enc = self.by_cmd[self.ENCODER]
        layout = struct_layout(enc)
        self.encoder_struct: struct.Struct | None = None
        if layout is not None and layout[1] == ("Pos_Estimate", "Vel_Estimate"):
            self.encoder_struct = layout[0]

    def _frame(self, node: int, cmd: int, values: dict[str, float]) -> can.Message:
        m = self.by_cmd[cmd]
        return can.Message(arbitration_id=node << 5 | cmd, data=m.encode(values, strict=False),
                           is_extended_id=False)

    # ---------------------------------------------------------------- host -> drive
    def mode_frame(self, node: int, interface: str) -> can.Message:
        return self._frame(node, self.SET_MODE, {"Control_Mode": self.CONTROL_MODES[interface],
                                                 "Input_Mode": self.INPUT_PASSTHROUGH})

    def state_frame(self, node: int, state: int) -> can.Message:
        return self._frame(node, self.SET_AXIS_STATE, {"Axis_Requested_State": state})

    def clear_errors_frame(self, node: int) -> can.Message:
        return self._frame(node, self.CLEAR_ERRORS, {"Identify": 0})

    def setup_frames(self, node: int, interface: str, hold: float | None) -> list[can.Message]:
        out = [self.mode_frame(node, interface)]
        if interface == "position" and hold is not None:
            out.append(self.command_frame(node, "position", hold, 0.0, 0.0))
        elif interface != "position":
            out.append(self.command_frame(node, interface, 0.0, 0.0, 0.0))
        out.append(self.state_frame(node, self.CLOSED_LOOP))
        return out

    def command_frame(self, node: int, interface: str, position: float, velocity: float,
                      torque: float) -> can.Message:
        if interface == "position":
            ff_v = max(-self.FF_LIMIT, min(self.FF_LIMIT, velocity / TAU))
            ff_t = max(-self.FF_LIMIT, min(self.FF_LIMIT, torque))
            return self._frame(node, self.INPUT_POS, {"Input_Pos": position / TAU, "Vel_FF": ff_v, "Torque_FF": ff_t})
        if interface == "velocity":
            return self._frame(node, self.INPUT_VEL, {"Input_Vel": velocity / TAU, "Input_Torque_FF": torque})
        if interface == "effort":
            return self._frame(node, self.INPUT_TORQUE, {"Input_Torque": torque})
        raise ValueError(f"unknown interface {interface!r}")

    def estimate_request(self, node: int) -> can.Message:
        return can.Message(arbitration_id=node << 5 | self.ENCODER, is_remote_frame=True, dlc=8,
                           is_extended_id=False)

    # ---------------------------------------------------------------- drive -> host
    def heartbeat_frame(self, hb: Heartbeat) -> can.Message:
        return self._frame(hb.node, self.HEARTBEAT, {
            "Axis_Error": hb.error, "Axis_State": hb.state, "Procedure_Result": hb.procedure_result,
            "Trajectory_Done_Flag": int(hb.trajectory_done)})

    def estimate_frame(self, est: Estimate) -> can.Message:
        return self._frame(est.node, self.ENCODER, {"Pos_Estimate": est.position / TAU,
                                                    "Vel_Estimate": est.velocity / TAU})

    # ---------------------------------------------------------------- parsing
    def direction(self, msg: can.Message) -> str | None:
        if msg.is_extended_id:
            return None
        cmd = msg.arbitration_id & 0x1F
        if cmd == self.HEARTBEAT or (cmd == self.ENCODER and not msg.is_remote_frame):
            return "to_host"
        if cmd in self.by_cmd:
            return "to_drive"
        return None

    def parse(self, msg: can.Message) -> Heartbeat | Estimate | DriveCommand:
        if msg.is_extended_id or msg.is_error_frame:
            raise FrameError("unknown_id", f"id 0x{msg.arbitration_id:X}: not an 11-bit data frame")
        node, cmd = msg.arbitration_id >> 5, msg.arbitration_id & 0x1F
        if cmd == self.ENCODER and self.encoder_struct is not None and len(msg.data) == 8 \
                and not msg.is_remote_frame:
            pos, vel = self.encoder_struct.unpack(msg.data)
            if math.isfinite(pos) and math.isfinite(vel):
                return Estimate(node, pos * TAU, vel * TAU)
            # else cantools below says what is wrong with it
        m = self.by_cmd.get(cmd)
        if m is None:
            raise FrameError("unknown_id", f"id 0x{msg.arbitration_id:03X}: command 0x{cmd:02X} is not handled")
        if msg.is_remote_frame:
            if cmd == self.ENCODER:
                return DriveCommand(node, "request_estimate")
            raise FrameError("unknown_id", f"id 0x{msg.arbitration_id:03X}: remote frame for {m.name}")
        if len(msg.data) != m.length:
            raise FrameError("bad_length", f"{m.name} (id 0x{msg.arbitration_id:03X}) with {len(msg.data)} "
                                           f"bytes, expected {m.length}")
        try:
            v: dict[str, Any] = m.decode(bytes(msg.data), decode_choices=False)
        except Exception as e:  # cantools raises several kinds; any of them is a malformed frame
            raise FrameError("malformed", f"{m.name} (id 0x{msg.arbitration_id:03X}): {e}") from None
        if any(isinstance(x, float) and not math.isfinite(x) for x in v.values()):
            raise FrameError("malformed", f"{m.name} (id 0x{msg.arbitration_id:03X}): non-finite value {v}")
        if cmd == self.HEARTBEAT:
            return Heartbeat(node, int(v["Axis_Error"]), int(v["Axis_State"]), int(v["Procedure_Result"]),
                             bool(v["Trajectory_Done_Flag"]))
        if cmd == self.ENCODER:
            return Estimate(node, float(v["Pos_Estimate"]) * TAU, float(v["Vel_Estimate"]) * TAU)
        if cmd == self.SET_AXIS_STATE:
            return DriveCommand(node, "state", int(v["Axis_Requested_State"]))
        if cmd == self.SET_MODE:
            return DriveCommand(node, "mode", int(v["Control_Mode"]), int(v["Input_Mode"]))
        if cmd == self.INPUT_POS:
            return DriveCommand(node, "position", float(v["Input_Pos"]) * TAU, float(v["Vel_FF"]) * TAU,
                                float(v["Torque_FF"]))
        if cmd == self.INPUT_VEL:
            return DriveCommand(node, "velocity", 0.0, float(v["Input_Vel"]) * TAU, float(v["Input_Torque_FF"]))
        if cmd == self.INPUT_TORQUE:
            return DriveCommand(node, "torque", c=float(v["Input_Torque"]))
        return DriveCommand(node, "clear_errors")


def struct_layout(message: Any) -> tuple[struct.Struct, tuple[str, ...]] | None:
    """A :class:`struct.Struct` that unpacks a cantools ``message`` exactly as its ``decode``
    does (``decode_choices=False``), with the signal names in its order; None where there is
    none: a signal not byte-aligned, big-endian, scaled or offset, multiplexed, or overlapping."""
    if message.is_multiplexed():
        return None
    fmt, names, at = "<", [], 0
    for sig in sorted(message.signals, key=lambda s: s.start):
        if sig.byte_order != "little_endian" or sig.start % 8 or sig.scale != 1 or sig.offset != 0 \
                or sig.start < at * 8:
            return None
        if sig.is_float:
            code = {32: "f", 64: "d"}.get(sig.length)
        else:
            code = {8: "b", 16: "h", 32: "i", 64: "q"}.get(sig.length)
            if code is not None and not sig.is_signed:
                code = code.upper()
        if code is None:
            return None
        fmt += "x" * (sig.start // 8 - at) + code
        at = sig.start // 8 + sig.length // 8
        names.append(sig.name)
    fmt += "x" * (message.length - at)
    if at > message.length:
        return None
    return struct.Struct(fmt), tuple(names)


# -------------------------------------------------------------------- lookup
@cache
def _plugins() -> dict[str, Any]:
    return {ep.name: ep for ep in entry_points(group=GROUP)}


def profile_names() -> list[str]:
    return [*PROFILES, *sorted(n for n in _plugins() if n not in PROFILES)]


def make_profile(name: str, dbc: Path | None = None) -> DriveProfile:
    """The profile called ``name`` (built in, else a ``hilsim.can_profiles`` plug-in)."""
    target = PROFILES.get(name)
    if target is not None:
        module, _, attr = target.partition(":")
        cls = getattr(importlib.import_module(module), attr)
    else:
        ep = _plugins().get(name)
        if ep is None:
            raise ConfigError(f"unknown CAN profile {name!r}; available: {', '.join(profile_names())}")
        cls = ep.load()
    if not (isinstance(cls, type) and issubclass(cls, DriveProfile)):
        raise ConfigError(f"CAN profile {name!r} is not a DriveProfile class")
    return cls(dbc) if dbc is not None else cls()
