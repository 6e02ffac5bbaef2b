"""Services of other hosts (``hilsim up --only``, docs/deployment.md): their comings and goings.

The launcher starts only this host's services and waits for the others' liveliness tokens; this
part of it (:class:`RemoteHosts`, a base of :class:`hilsim.launch.launcher.Launcher`) keeps which remote
service is up, says when one leaves or comes back, asks who is alive with a liveliness query when a
departure event may have been lost (:meth:`RemoteHosts._poll_remote`), and holds the recorder's stop
until the other hosts' services have left (:meth:`RemoteHosts._await_remote_leaving`).

Reads: ``<prefix>/<robot>/alive/*`` (every robot's ``<prefix>/*/alive/*`` with ``robots: N``) by a
liveliness query. Writes no key.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import zenoh

from hilsim.core import fleet
from hilsim.core.config import Scenario
from hilsim.core.keys import Keys
from hilsim.launch.follow import Outcome

REMOTE_LEAVE_TIMEOUT = 10.0  # s the recorder waits, at a run's end, for the other hosts' services to leave
REMOTE_MISSES = 2  # --only: polls in a row that must miss a remote service's token before it has left
REMOTE_GRACE_S = 10.0  # --only: how long a departed remote writer's samples are still its own


class RemoteHosts:
    """The launcher's view of the services of other hosts (the launcher sets these attributes)."""

    sc: Scenario
    session: zenoh.Session
    follow_keys: Keys
    lock: threading.Lock
    hurry: bool
    remote: dict[str, bool]  # remote service -> alive now
    remote_left: dict[str, float]  # remote service -> monotonic time it left
    remote_missed: dict[str, int]  # remote service -> polls in a row that did not find it
    say: Callable[[str], None]
    outcome: Outcome  # the run so far (the launcher's: interrupted, it waits for no one)

    def _on_remote(self, svc: str, up: bool) -> None:
        """A service of another host announced itself or left (under self.lock)."""
        was = self.remote[svc]
        self.remote[svc] = up
        if up and svc in self.remote_left:
            self.say(f"  remote {svc} is back, {time.monotonic() - self.remote_left.pop(svc):.1f} s after it left")
        elif was and not up:
            self.remote_left[svc] = time.monotonic()
            self.say(f"  remote {svc} left (its host's launcher may restart it)")

    def _poll_remote(self) -> None:
        """Ask who is alive: a remote service's departure must not hang on one liveliness event
        (seen lost through the router under load), so the run still ends, bounded. A service counts
        as gone only when ``REMOTE_MISSES`` polls in a row did not find it: one query's reply can miss
        a token that is there (seen at a run's start: "left", then "back" 2 s later, though nothing
        had left); a reply without any token at all (this host's services answer too) says nothing."""
        try:
            replies = self.session.liveliness().get(self.follow_keys.all_alive, timeout=1.0)
            alive = {fleet.service_id(self.sc, str(r.ok.key_expr), "alive") for r in replies if r.ok is not None}
        except zenoh.ZError:
            return
        if not alive:
            return
        with self.lock:
            for svc, up in list(self.remote.items()):
                if svc in alive:
                    self.remote_missed.pop(svc, None)
                    if not up and svc in self.remote_left:  # back
                        self._on_remote(svc, True)
                elif up:
                    self.remote_missed[svc] = self.remote_missed.get(svc, 0) + 1
                    if self.remote_missed[svc] >= REMOTE_MISSES:  # left, its departure event lost
                        self.remote_missed.pop(svc)
                        self._on_remote(svc, False)

    def _await_remote_leaving(self, timeout: float = REMOTE_LEAVE_TIMEOUT) -> None:
        """Several hosts: the recorder here stops once the other hosts' services have left (bounded), so
        that what they sent last (their final health, counted in what they published) reaches it: one
        host's recorder stopped first once, and a run that had lost nothing ended FAILED. Not when this host
        was interrupted: the others may go on."""
        if self.outcome.interrupted:
            return
        end = time.monotonic() + timeout
        waited = False
        last_poll = time.monotonic()
        while time.monotonic() < end and not self.hurry:
            with self.lock:
                up = [s for s, on in self.remote.items() if on]
            if not up:
                break
            waited = True
            if time.monotonic() - last_poll > 1.0:  # a departure event can be lost (_poll_remote)
                last_poll = time.monotonic()
                self._poll_remote()
            time.sleep(0.05)
        if waited:
            time.sleep(0.2)  # a sample put just before a token went may reach the recorder after the token's news
