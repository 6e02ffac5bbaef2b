"""What the bridges' links share: :class:`KeptOpen`, the CAN bus's (:class:`bridges.can_bus.CanLink`)
and the MAVLink connection's (:class:`bridges.mavlink_link.MavLink`) way of keeping themselves open;
and :class:`OncePer`, how often the bridges and device emulators say the same kind of bad input.

A reader thread opens the link with ``opener(cfg)`` (which raises :class:`ConnectionError` with
one line when it cannot), reads it, and when it cannot be opened or fails, closes it, calls
``on_state(False, reason)`` once per outage, and reopens it every ``reconnect_interval`` s;
``on_state(True, "")`` once it works again. Sending never raises: a refused frame is counted.

A subclass says how one read goes (:meth:`KeptOpen._read`), how a frame is written
(:meth:`KeptOpen._write`) and how the link's handle is closed (:meth:`KeptOpen._shutdown`); the
other hooks are optional.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar


class KeptOpen:
    """The keep-open machinery of a link; ``handle`` is the open bus or connection (None: closed)."""

    SEND_ERRORS: ClassVar[tuple[type[BaseException], ...]] = (Exception,)  # a send that raises these is refused

    def __init__(self, cfg: Any, opener: Callable[[Any], Any], on_state: Callable[[bool, str], None], *,
                 name: str, logger: str, reconnect_interval: float) -> None:
        self.cfg = cfg
        self.opener = opener
        self.on_state = on_state
        self.reconnect_interval = reconnect_interval
        self.log = logging.getLogger(f"hilsim.{name}.{logger}")
        self.handle: Any = None
        self.up = False
        self.reason = ""
        self._stop = threading.Event()
        self._send_lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, daemon=True, name=f"{name}-rx")
        self.rx = self.tx = self.tx_failed = self.outages = 0

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        self._close()

    def send(self, msg: Any) -> bool:
        """Write one frame; False (counted in ``tx_failed``) if the link is down or refused it."""
        handle = self.handle
        if handle is None or not self.up:
            self.tx_failed += 1
            return False
        try:
            with self._send_lock:
                self._write(handle, msg)
        except self.SEND_ERRORS as e:
            self.tx_failed += 1
            self._refused(e)
            return False
        self._sent()
        self.tx += 1
        return True

    # ---------------------------------------------------------------- what a subclass gives
    def _read(self) -> bool:
        """One read of the open link (it handles what came); False if the link went down (the
        reader waits ``reconnect_interval`` before it reopens it)."""
        raise NotImplementedError

    def _write(self, handle: Any, msg: Any) -> None:
        raise NotImplementedError

    def _shutdown(self, handle: Any) -> None:
        raise NotImplementedError

    def _opened(self) -> None:
        """Just opened (before ``on_state(True, "")``)."""

    def _closed(self) -> None:
        """Just closed on an outage (before ``on_state(False, reason)``)."""

    def _refused(self, e: BaseException) -> None:
        """A send raised ``e``."""

    def _sent(self) -> None:
        """A send went."""

    # ---------------------------------------------------------------- reader thread
    def _close(self) -> None:
        handle, self.handle = self.handle, None
        if handle is not None:
            try:
                self._shutdown(handle)
            except Exception:  # a link that failed may fail to close too
                pass

    def _down(self, reason: str) -> None:
        self._close()
        self._closed()
        if self.up or not self.reason:
            self.outages += 1
            self.up = False
            self.reason = reason
            self.on_state(False, reason)

    def _open(self) -> bool:
        try:
            self.handle = self.opener(self.cfg)
        except ConnectionError as e:
            if self.reason != str(e):
                self.up = True  # so that _down reports this new reason
            self._down(str(e))
            return False
        self._opened()
        self.up, self.reason = True, ""
        self.on_state(True, "")
        return True

    def _run(self) -> None:
        while not self._stop.is_set():
            if (self.handle is None and not self._open()) or not self._read():
                self._stop.wait(self.reconnect_interval)


class OncePer:
    """``due(kind)``: True at most once every ``every`` seconds per kind (monotonic clock), so that
    input that keeps coming bad is said now and then, not once a frame."""

    def __init__(self, every: float = 5.0) -> None:
        self.every = every
        self._last: dict[str, float] = {}

    def due(self, kind: str) -> bool:
        now = time.monotonic()
        if now - self._last.get(kind, -1e9) > self.every:
            self._last[kind] = now
            return True
        return False
