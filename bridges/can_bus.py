"""What the CAN bridge and the drive emulator share: the bus settings, the joint <-> motor mapping,
:class:`CanLink`, a python-can bus that opens, reads, sends and reopens on its own, and
:class:`UnusedFrames`, how they count and say the frames they cannot use.

The bus is any python-can interface: ``interface`` and ``channel`` as python-can names them, any
other field is passed to ``can.Bus`` as it is (``bitrate``, ``port``, ``hop_limit``, ``fd``, …)::

    bus: {interface: socketcan, channel: can0}
    bus: {interface: udp_multicast, channel: "ff15:7079:7468:6f6e:6465:6d6f:6d63:6173", port: 43113}
    bus: {interface: virtual, channel: test}          # in one process only
    bus: {interface: pcan, channel: PCAN_USBBUS1, bitrate: 1000000}

python-can's default IPv6 group needs IPv6 multicast, which containers and some hosts lack:
:func:`resolve_bus` then takes python-can's IPv4 group (``239.74.163.2``) instead, the same way in
every process of the host (each probes IPv6 once), so the bridge and the drive emulator still
meet. A bus that cannot be opened says why and what to change (:func:`open_bus`).
"""

from __future__ import annotations

import ipaddress
import logging
import math
import os
import socket
import struct
import time
from collections import Counter
from collections.abc import Callable, Iterable
from typing import Any, Literal

import can
from pydantic import BaseModel, ConfigDict, Field

from hilsim.bridges.link import KeptOpen, OncePer

# python-can's udp_multicast defaults (can.interfaces.udp_multicast.UdpMulticastBus)
UDP_GROUP_IPV6 = "ff15:7079:7468:6f6e:6465:6d6f:6d63:6173"
UDP_GROUP_IPV4 = "239.74.163.2"
UDP_PORT = 43113
IPV4_ROUTE_HINT = "ip route add 224.0.0.0/4 dev lo"  # IPv4 multicast between the processes of one host
# SocketCAN error frame class bits (linux/can/error.h)
CAN_ERR_BUSOFF = 0x40
CAN_ERR_RESTARTED = 0x100


class BusConfig(BaseModel):
    """A python-can bus: ``interface``, ``channel``, and any other ``can.Bus`` argument."""

    model_config = ConfigDict(extra="allow")
    interface: str = Field("udp_multicast", description="python-can interface: socketcan, udp_multicast, "
                           "virtual, pcan, slcan, …")
    channel: str = Field(UDP_GROUP_IPV6, description="python-can channel (can0, a multicast group, …)")

    def extra(self) -> dict[str, Any]:
        """The other ``can.Bus`` arguments; one set to null (e.g. an overlay's ``port: null``) is left out."""
        return {k: v for k, v in (self.model_extra or {}).items() if v is not None}

    def kwargs(self) -> dict[str, Any]:
        return {"interface": self.interface, "channel": self.channel, **self.extra()}

    def describe(self) -> str:
        extra = "".join(f" {k}={v}" for k, v in self.extra().items())
        return f"{self.interface}:{self.channel}{extra}"


class JointMap(BaseModel):
    """One joint on the bus: the drive's node id and how the motor relates to the joint.

    ``motor = direction · gear_ratio · (joint − offset)`` (rad; velocities without the offset;
    torque: ``motor = direction · joint / gear_ratio``). ``offset`` is the joint position [rad]
    at which the motor encoder reads zero."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    node_id: int = Field(ge=0, le=63, description="CAN node id of the drive (axis)")
    gear_ratio: float = Field(1.0, gt=0, description="motor turns per joint turn")
    direction: Literal[1, -1] = 1
    offset: float = Field(0.0, description="joint position [rad] where the motor encoder reads 0")

    def to_motor(self, q: float) -> float:
        return self.direction * self.gear_ratio * (q - self.offset)

    def to_joint(self, m: float) -> float:
        return self.direction * m / self.gear_ratio + self.offset

    def vel_to_motor(self, dq: float) -> float:
        return self.direction * self.gear_ratio * dq

    def vel_to_joint(self, dm: float) -> float:
        return self.direction * dm / self.gear_ratio

    def torque_to_motor(self, tau: float) -> float:
        return self.direction * tau / self.gear_ratio

    def torque_to_joint(self, tau_m: float) -> float:
        return self.direction * tau_m * self.gear_ratio


def open_bus(cfg: BusConfig) -> can.BusABC:
    """Open the bus; :class:`ConnectionError` with one line if it is not available (for
    udp_multicast: the system's reason, and what to change)."""
    try:
        return can.Bus(**cfg.kwargs())
    except (can.CanError, OSError, ImportError, ValueError, TypeError, NotImplementedError) as e:
        why = f"{type(e).__name__}: {e}"
        cause = e.__cause__ or e.__context__
        if isinstance(cause, OSError) and not isinstance(e, OSError):  # python-can hides the system's reason
            why = f"{e} ({cause.strerror or cause})"
        raise ConnectionError(f"CAN bus {cfg.describe()} not available: {why}{_udp_hint(cfg)}") from None


def _ip_version(group: str) -> int | None:
    try:
        return ipaddress.ip_address(group).version
    except ValueError:
        return None


def _udp_hint(cfg: BusConfig) -> str:
    """What to do about a udp_multicast bus that does not open ("" for other interfaces)."""
    if cfg.interface != "udp_multicast":
        return ""
    v, v6 = _ip_version(cfg.channel), ipv6_multicast_problem()
    if v == 6:
        what = f"no IPv6 multicast on this host ({v6})" if v6 else "IPv6 multicast may not reach this group"
        return (f"; {what}: use python-can's IPv4 group, bus.channel {UDP_GROUP_IPV4} "
                f"(e.g. --set bridge-can.bus.channel={UDP_GROUP_IPV4})")
    if v == 4:
        return (f"; IPv4 multicast needs a route (on one host: {IPV4_ROUTE_HINT})"
                + (f"; no IPv6 multicast either ({v6})" if v6 else ""))
    return ""


_ipv6_probe: str | None = None  # None: not probed yet; "": IPv6 multicast works; else why not


def ipv6_multicast_problem() -> str:
    """Why a UDP socket of this host cannot join python-can's IPv6 group ("" if it can), as its
    udp_multicast bus would (``IPV6_JOIN_GROUP`` on the default interface); probed once per process."""
    global _ipv6_probe
    if _ipv6_probe is None:
        try:
            with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as s:
                group = socket.inet_pton(socket.AF_INET6, UDP_GROUP_IPV6) + struct.pack("@I", 0)
                s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_JOIN_GROUP, group)
            _ipv6_probe = ""
        except OSError as e:
            _ipv6_probe = e.strerror or str(e)
    return _ipv6_probe


def resolve_bus(cfg: BusConfig, log: logging.Logger) -> BusConfig:
    """The bus to open for ``cfg``: ``cfg`` itself, except python-can's default IPv6 group on a host
    without IPv6 multicast, which becomes python-can's IPv4 group (same port), said in ``log``.
    Every process of a host decides alike (the same probe), so the two ends of the bus still meet;
    a group the scenario chose otherwise is never changed."""
    if cfg.interface != "udp_multicast" or _ip_version(cfg.channel) != 6:
        return cfg
    if ipaddress.ip_address(cfg.channel) != ipaddress.ip_address(UDP_GROUP_IPV6):
        return cfg
    why = ipv6_multicast_problem()
    if not why:
        return cfg
    log.warning("IPv6 multicast is not available on this host (%s): the CAN bus uses python-can's IPv4 "
                "group %s instead (every process of this host does the same; set bus.channel to choose)",
                why, UDP_GROUP_IPV4)
    return cfg.model_copy(update={"channel": UDP_GROUP_IPV4})


def is_bus_off(msg: can.Message) -> bool:
    """An error frame saying the controller went bus-off (SocketCAN's error class bits)."""
    return bool(msg.is_error_frame and msg.arbitration_id & CAN_ERR_BUSOFF)


class CanLink(KeptOpen):
    """A bus that keeps itself open (:class:`bridges.link.KeptOpen`): a reader thread hands every
    data frame to ``on_frame`` and, when the bus cannot be opened, fails to receive, goes bus-off,
    reports an error state or keeps refusing frames, closes it, calls ``on_state(False, reason)``
    (once per outage), and reopens it every ``reconnect_interval`` s; ``on_state(True, "")`` once
    it works again. Sending never raises: a refused frame is counted.

    With ``on_batch_end``, the reader drains the bus after each frame it waited for: it goes on
    reading what is already there (``recv(timeout=0)``, any interface) for at most
    ``batch_window`` seconds after the first frame came, hands each frame to ``on_frame`` as
    before, then calls ``on_batch_end()`` once. A busy bus's frames that arrived together are
    thus answered together (the bridge publishes the newest state once per batch instead of
    once per frame), and no frame waits in the batch longer than ``batch_window``.

    ``rx_buffer`` (bytes, 0: the system's default): the receive buffer asked for on the bus's
    socket (interfaces with one: socketcan, udp_multicast), so that frames arriving while this
    process is not scheduled wait there instead of being dropped by the kernel (the default
    holds ~256 udp_multicast frames, 36 ms of a saturated bus); the kernel caps it at
    ``net.core.rmem_max``."""

    SEND_FAILURES_DOWN = 50  # consecutive refused frames that count as the bus being down
    SEND_ERRORS = (can.CanError, OSError, ValueError)

    def __init__(self, cfg: BusConfig, on_frame: Callable[[can.Message], None],
                 on_state: Callable[[bool, str], None], *, reconnect_interval: float = 1.0,
                 name: str = "can", opener: Callable[[BusConfig], can.BusABC] = open_bus,
                 on_batch_end: Callable[[], None] | None = None, batch_window: float = 3e-4,
                 rx_buffer: int = 0) -> None:
        super().__init__(cfg, opener, on_state, name=name, logger="bus", reconnect_interval=reconnect_interval)
        self.on_frame = on_frame
        self.on_batch_end, self.batch_window = on_batch_end, batch_window
        self.rx_buffer = rx_buffer
        self.rx_buffer_granted: int | None = None  # bytes, as the kernel reports it (None: not set)
        self._reopen: str | None = None  # set by a sender that saw the bus fail; the reader acts on it
        self.error_frames = 0
        self.batches = 0  # on_batch_end calls
        self._consecutive_failures = 0
        self._next_state_check = 0.0
        self.opened_once = False
        self._open_timeout = 0.0
        self._open_deadline = math.inf

    @property
    def bus(self) -> can.BusABC | None:
        return self.handle

    def start_or_fail(self, open_timeout: float) -> None:
        """Start, insisting on the bus at start: with ``open_timeout`` 0 it is opened here, and a bus
        that cannot be opened raises :class:`ConnectionError` (one line: why, and what to change);
        else the reader keeps trying (faults said as usual) and :meth:`check_opened` raises once
        ``open_timeout`` s have passed without it ever opening. Once it has been open, an outage is
        only a fault: the reader reopens it however long that takes."""
        if open_timeout <= 0:
            self.handle = self.opener(self.cfg)
            self._opened()
            self.up, self.reason = True, ""
            self.on_state(True, "")
        else:
            self._open_timeout = open_timeout
            self._open_deadline = time.monotonic() + open_timeout
        self.start()

    def check_opened(self) -> None:
        """:class:`ConnectionError` if the bus never opened within :meth:`start_or_fail`'s ``open_timeout``."""
        if not self.opened_once and time.monotonic() > self._open_deadline:
            raise ConnectionError(f"not opened within open_timeout ({self._open_timeout:g} s): "
                                  f"{self.reason or 'CAN bus not available'}")

    # ---------------------------------------------------------------- KeptOpen's hooks
    def _write(self, handle: can.BusABC, msg: can.Message) -> None:
        handle.send(msg, timeout=0.005)

    def _refused(self, e: BaseException) -> None:
        self._consecutive_failures += 1
        if self._consecutive_failures >= self.SEND_FAILURES_DOWN and self._reopen is None:
            self._reopen = f"{self._consecutive_failures} frames in a row refused ({e})"

    def _sent(self) -> None:
        self._consecutive_failures = 0

    def _shutdown(self, handle: can.BusABC) -> None:
        handle.shutdown()

    def _opened(self) -> None:
        self.opened_once = True
        self._consecutive_failures = 0
        self._reopen = None
        if self.rx_buffer > 0:
            self.rx_buffer_granted = grow_rx_buffer(self.handle, self.rx_buffer)
            self.log.info("receive buffer: %s bytes asked, %s granted", self.rx_buffer,
                          self.rx_buffer_granted if self.rx_buffer_granted is not None
                          else "none (the interface has no socket)")

    # ---------------------------------------------------------------- reader thread
    def _read(self) -> bool:
        if self._reopen is not None:
            self._down(self._reopen)
            return False
        try:
            msg = self.handle.recv(0.05)
        except (can.CanError, OSError, ValueError) as e:
            self._down(f"receive failed: {type(e).__name__}: {e}")
            return False
        now = time.monotonic()
        if now >= self._next_state_check:
            self._next_state_check = now + 0.5
            if _bus_state(self.handle) == can.BusState.ERROR:
                self._down("bus-off (the interface reports an error state)")
                return True  # reopened at once
        if msg is None:
            return True
        if self.on_batch_end is None:
            return self._take(msg)
        return self._drain(msg)

    def _take(self, msg: can.Message) -> bool:
        """Hand one received frame on; False if it said the bus went off (it is closed then)."""
        if msg.is_error_frame:
            self.error_frames += 1
            if is_bus_off(msg):
                self._down("bus-off (error frame from the controller)")
                return False
            return True
        self.rx += 1
        try:
            self.on_frame(msg)
        except Exception as e:  # the owner's bug must not end the reader
            self.log.exception("frame handler failed: %s", e)
        return True

    def _drain(self, first: can.Message) -> bool:
        """``first`` and whatever else is readable now (within ``batch_window``), then ``on_batch_end``;
        False if the bus went down meanwhile."""
        end = time.monotonic() + self.batch_window
        ok = self._take(first)
        bus = self.handle
        try:
            while ok and bus is not None and time.monotonic() < end:
                msg = bus.recv(0)
                if msg is None:
                    break
                ok = self._take(msg)
        except (can.CanError, OSError, ValueError) as e:
            self._down(f"receive failed: {type(e).__name__}: {e}")
            ok = False
        self.batches += 1
        assert self.on_batch_end is not None
        try:
            self.on_batch_end()
        except Exception as e:
            self.log.exception("batch handler failed: %s", e)
        return ok


def grow_rx_buffer(bus: can.BusABC, size: int) -> int | None:
    """Set SO_RCVBUF of the bus's socket (python-can's ``fileno()``) to ``size`` bytes; what the
    kernel granted (it doubles the figure for its bookkeeping and caps it at rmem_max), or None
    where the interface has no socket."""
    try:
        fd = bus.fileno()
    except (NotImplementedError, AttributeError, OSError):
        return None
    if not isinstance(fd, int) or fd < 0:
        return None
    try:
        s = socket.socket(fileno=os.dup(fd))  # a second handle on the same socket, closed below
    except OSError:
        return None
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
        return int(s.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
    except OSError:
        return None
    finally:
        s.close()


def _bus_state(bus: can.BusABC) -> Any:
    try:
        return bus.state
    except Exception:
        return None


class UnusedFrames:
    """``unused(kind, text)``: a frame a CAN service could not use, counted per kind in ``counts`` (its
    health's ``frames_<kind>``) and in the service's ``rejected`` as ``can:<kind>``, and said (``warn``)
    at most once every 5 s per kind."""

    def __init__(self, kinds: Iterable[str], rejected: Counter[str], warn: Callable[[str], None]) -> None:
        self.counts: dict[str, int] = dict.fromkeys(kinds, 0)
        self._rejected, self._warn = rejected, warn
        self._said = OncePer(5.0)

    def __call__(self, kind: str, text: str) -> None:
        self.counts[kind] += 1
        self._rejected[f"can:{kind}"] += 1
        if self._said.due(kind):
            self._warn(f"CAN frame not used ({kind}, {self.counts[kind]} so far): {text}")


def raise_priority(priority: int, log: logging.Logger) -> None:
    """Ask for SCHED_FIFO ``priority`` for every thread of this process (as physics does in realtime):
    a drive and its bridge live on the wall clock, and a loaded machine must not starve their
    heartbeats. Without the privilege (root or CAP_SYS_NICE), say so and go on. 0: do not ask."""
    if priority <= 0:
        return
    try:
        for tid in sorted(int(t) for t in os.listdir("/proc/self/task")):
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
        log.info("running with SCHED_FIFO priority %d", priority)
    except (PermissionError, AttributeError, OSError) as e:
        log.warning("could not get a real-time scheduling class (%s); heartbeats may be late on a loaded machine", e)


def finite(*xs: float) -> bool:
    return all(math.isfinite(x) for x in xs)
