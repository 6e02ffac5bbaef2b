"""Physics' external joint servers: joints moved by measured state from outside, and their silence.

A part of :class:`hilsim.services.physics.PhysicsService` (one of its bases, not a service of its own).
A scenario's joint with an external server (a single robot only) is not simulated: physics makes it
follow the server's measured state. A server silent for ``physics.server_timeout`` (wall time) is a
fault, said once (published on ``log/physics``), its joints held at the last measured position; said
again when it reports again.

Reads ``<prefix>/<robot>/hw/<server>/joint_states`` (sensor_msgs/JointState, measured by the server).
Writes nothing of its own (faults through the service; ``servers_silent`` in physics' health).
"""

from __future__ import annotations

import time

from hilsim.core import msgs
from hilsim.core.keys import topic_name
from hilsim.services.physics_truth import PhysicsTruth


class PhysicsServers(PhysicsTruth):
    """Physics' external joint servers (:class:`hilsim.services.physics.PhysicsService` sets these attributes)."""

    servers: dict[str, set[str]]  # which joints each server serves
    server_seen: dict[str, float]  # [monotonic s] when each last reported
    server_silent: set[str]
    wall_start: float

    # ------------------------------------------------------------------ external joint servers
    def _on_server_state(self, js: msgs.JointState, key: str) -> None:
        server = topic_name(key).split("/")[-2]  # …/hw/<server>/joint_states
        served = self.servers.get(server)
        if served is None:
            raise msgs.BadMessage(f"{server!r} serves no joint in this scenario")
        stray = [n for n in js.name if n not in served]
        if stray:
            raise msgs.BadMessage(f"{server} reports joints it does not serve: {stray}")
        if len(js.position) != len(js.name):
            raise msgs.BadMessage("joint server state without positions")
        self.robots[0].world.follow(list(js.name), list(js.position), list(js.velocity))
        self.server_seen[server] = time.monotonic()
        if server in self.server_silent:
            self.server_silent.discard(server)
            self.log.info("joint server %s reports again (t=%.3f s)", server, self.sim_ns / 1e9)

    def _check_servers(self) -> None:
        """A joint server silent for physics.server_timeout (wall) is a fault, said once."""
        now = time.monotonic()
        for server, joints in self.servers.items():
            last = self.server_seen.get(server, self.wall_start)
            if now - last > self.sc.physics.server_timeout and server not in self.server_silent:
                self.server_silent.add(server)
                self.robots[0].world.hold(sorted(joints))
                self.fault(f"joint server {server} silent for {now - last:.2f} s at t={self.sim_ns / 1e9:.3f}s: "
                           f"{', '.join(sorted(joints))} held at the last measured position")
