"""What the MAVLink bridge and the GPS emulator share: the link settings and :class:`MavLink`, a
pymavlink connection that opens, reads, sends and reopens on its own.

The connection is any string pymavlink's ``mavutil.mavlink_connection`` takes::

    connection: udpin:127.0.0.1:14550     # listen for UDP datagrams (a GPS, a companion, an autopilot)
    connection: udpout:192.168.1.10:14550 # send to that address (replies come back to our port)
    connection: tcp:127.0.0.1:5760        # connect to a TCP server (e.g. ArduPilot SITL)
    connection: /dev/ttyACM0              # a serial device, at ``baud``
    connection: /dev/ttyUSB0,57600        # or with its baud rate, as pymavlink also takes it

pymavlink's connection objects carry a parser of the process-wide dialect that mavutil picks
from the environment; here they are only the transport. Every link parses with its own
``MAVLink`` object of the MAVLink 2 **common** dialect (:mod:`pymavlink.dialects.v20.common`),
which reads MAVLink 1 and MAVLink 2 frames alike, in robust mode: a frame with a bad CRC, bytes
that are not a frame, and a message id the dialect does not know are each counted and handed to
``on_bad``, never raised. Outgoing frames are MAVLink 2 unless ``mavlink1`` is set.
"""

from __future__ import annotations

import select
import time
from collections.abc import Callable
from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from pymavlink.dialects.v20 import common as mavlink

from hilsim.bridges.link import KeptOpen

# what the count of bad input is kept under (health ``mavlink_<kind>``)
BAD_CRC, BAD_DATA, UNKNOWN = "bad_crc", "bad_data", "unknown_id"


class LinkConfig(BaseModel):
    """One MAVLink connection and who we are on it."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    connection: str = Field("udpin:127.0.0.1:14550", min_length=1,
                            description="pymavlink connection string: udpin:HOST:PORT, udpout:HOST:PORT, "
                            "tcp:HOST:PORT, or a serial device (with baud)")
    baud: int = Field(115200, gt=0, description="serial devices only: baud rate")
    system_id: int = Field(255, ge=1, le=255, description="our MAVLink system id")
    component_id: int = Field(191, ge=0, le=255, description="our MAVLink component id (191: onboard computer)")
    mavlink1: bool = Field(False, description="send MAVLink 1 frames (received frames may be either)")
    heartbeat_period: float = Field(1.0, gt=0, description="[s] between our HEARTBEATs")
    reconnect_interval: float = Field(1.0, gt=0, description="[s] between attempts to reopen a failed link")

    def describe(self) -> str:
        serial = self.connection.split(":", 1)[0] not in ("udpin", "udpout", "udpbcast", "udp", "tcp", "tcpin")
        return f"{self.connection}" + (f" at {self.baud} baud" if serial and "," not in self.connection else "")

    @property
    def is_stream(self) -> bool:
        """A byte stream (TCP, serial) rather than datagrams: an empty read means it closed."""
        return not self.connection.startswith(("udpin:", "udpout:", "udpbcast:", "udp:"))


def open_connection(cfg: LinkConfig) -> Any:
    """The pymavlink connection object; :class:`ConnectionError` with one line if it cannot be opened."""
    from pymavlink import mavutil

    try:
        return mavutil.mavlink_connection(cfg.connection, baud=cfg.baud, source_system=cfg.system_id,
                                          source_component=cfg.component_id, retries=0, autoreconnect=False)
    except Exception as e:  # socket, serial and pymavlink errors alike: the reason in one line
        raise ConnectionError(f"MAVLink link {cfg.describe()} not available: {type(e).__name__}: {e}") from None


class _Writer:
    """The file object a ``MAVLink`` encoder writes to: the present connection, if any."""

    def __init__(self, link: MavLink) -> None:
        self.link = link

    def write(self, buf: bytes) -> None:
        conn = self.link.conn
        if conn is None:
            raise ConnectionError("link down")
        conn.write(buf)


class MavLink(KeptOpen):
    """A MAVLink connection that keeps itself open (:class:`bridges.link.KeptOpen`): a reader thread
    parses what arrives and hands every message of the dialect to ``on_message(msg, t_rx)``
    (``t_rx``: ``time.perf_counter()`` when its bytes were read); bad CRCs, stray bytes and unknown
    message ids go to ``on_bad(kind, text)``. When the connection cannot be opened or fails, it is
    closed, ``on_state(False, reason)`` is called once per outage, and it is reopened every
    ``reconnect_interval`` s (``on_state(True, "")`` once it works). Sending never raises: ``send``
    encodes one message (MAVLink 2, or 1 with ``mavlink1``) and says whether it went."""

    def __init__(self, cfg: LinkConfig, on_message: Callable[[Any, float], None],
                 on_state: Callable[[bool, str], None], on_bad: Callable[[str, str], None], *, name: str = "mavlink",
                 opener: Callable[[LinkConfig], Any] = open_connection) -> None:
        super().__init__(cfg, opener, on_state, name=name, logger="link", reconnect_interval=cfg.reconnect_interval)
        self.on_message, self.on_bad = on_message, on_bad
        self.mav = mavlink.MAVLink(_Writer(self), srcSystem=cfg.system_id, srcComponent=cfg.component_id)
        self.mav.robust_parsing = True
        self.bad: dict[str, int] = {BAD_CRC: 0, BAD_DATA: 0, UNKNOWN: 0}
        self.by_type: dict[str, int] = {}

    @property
    def conn(self) -> Any:
        return self.handle

    def heartbeat(self, mav_type: int, autopilot: int = mavlink.MAV_AUTOPILOT_INVALID,
                  state: int = mavlink.MAV_STATE_ACTIVE) -> bool:
        return self.send(mavlink.MAVLink_heartbeat_message(mav_type, autopilot, 0, 0, state, 3))

    # ---------------------------------------------------------------- KeptOpen's hooks
    def _write(self, handle: Any, msg: Any) -> None:
        self.mav.send(msg, force_mavlink1=self.cfg.mavlink1)

    def _refused(self, e: BaseException) -> None:  # a closed socket, a serial port gone: the reader reopens it
        self.log.debug("send failed: %s", e)

    def _shutdown(self, handle: Any) -> None:
        handle.close()

    def _closed(self) -> None:
        self.mav.buf, self.mav.buf_index = bytearray(), 0  # a partial frame of the old link is gone

    # ---------------------------------------------------------------- reader thread
    def _read(self) -> bool:
        try:
            fd = self.handle.fd
            if fd is not None:
                ready, _, _ = select.select([fd], [], [], 0.1)
                if not ready:
                    return True
            data = self.handle.recv(4096)
            t_rx = time.perf_counter()
        except Exception as e:  # socket or serial errors: the link is down, reopen it
            self._down(f"receive failed: {type(e).__name__}: {e}")
            return False
        if not data:
            if self.cfg.is_stream and fd is not None:
                self._down("closed by the other end")
                return False
            if fd is None:
                self._stop.wait(0.005)
            return True
        self._parse(bytes(data) if not isinstance(data, bytes | bytearray) else data, t_rx)
        return True

    def _parse(self, data: bytes | bytearray, t_rx: float) -> None:
        try:
            found = self.mav.parse_buffer(data) or []
        except Exception as e:  # robust parsing raises nothing known; anything else is bad data
            self.mav.buf, self.mav.buf_index = bytearray(), 0
            found = [mavlink.MAVLink_bad_data(bytearray(data), f"{type(e).__name__}: {e}")]
        for msg in found:
            kind = _badness(msg)
            if kind is not None:
                self.bad[kind] += 1
                try:
                    self.on_bad(kind, _describe_bad(msg))
                except Exception as e:
                    self.log.exception("bad-data handler failed: %s", e)
                continue
            self.rx += 1
            t = msg.get_type()
            self.by_type[t] = self.by_type.get(t, 0) + 1
            try:
                self.on_message(msg, t_rx)
            except Exception as e:  # the owner's bug must not end the reader
                self.log.exception("message handler failed: %s", e)


def _badness(msg: Any) -> str | None:
    if isinstance(msg, mavlink.MAVLink_bad_data):
        return BAD_CRC if "CRC" in str(msg.reason) else BAD_DATA
    if isinstance(msg, mavlink.MAVLink_unknown) or msg.get_msgId() < 0:
        return UNKNOWN
    return None


def _describe_bad(msg: Any) -> str:
    if isinstance(msg, mavlink.MAVLink_bad_data):
        return f"{msg.reason} ({len(msg.data)} bytes)"
    d = bytes(msg.get_msgbuf())
    sys_, comp = (d[5], d[6]) if d[:1] == b"\xfd" and len(d) > 6 else (d[3], d[4]) if len(d) > 4 else (0, 0)
    msgid = msg.get_type().removeprefix("UNKNOWN_")
    return f"message id {msgid} from system {sys_} component {comp} is not in the common dialect"
