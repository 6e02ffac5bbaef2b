"""Physics' joint commands: each robot's, every robot's in one sample (robots as arrays), and the watchdog.

A part of :class:`hilsim.services.physics.PhysicsService` (one of its bases, not a service of its own).
A command acts on the step it answers: in lockstep from that step plus its writer's lag
(``clock.controller_lag``), kept until physics reaches that step; one stamped for another step is
refused. Written by a participant that acknowledges through ``joint_commands``, it is that
participant's acknowledgement (:mod:`hilsim.services.physics_lockstep`). Realtime, the controller or the
sensors gone: the simulated joints stop obeying the last command (as a drive's command watchdog does).

Reads ``<prefix>/<robot>/joint_commands`` (sensor_msgs/JointState: per joint, the field of its interface;
any subset) and, robots as arrays, ``<prefix>/<robot>/fleet/joint_commands`` (joints
``<robot><k>/<joint>``, each robot's slice acting as its own ``joint_commands`` would). Writes nothing.
"""

from __future__ import annotations

from hilsim.core import msgs
from hilsim.core.transport import Attachment
from hilsim.services.physics_lockstep import PhysicsLockstep
from hilsim.services.physics_truth import Robot
from hilsim.sim.world import World


class PhysicsCommands(PhysicsLockstep):
    """Physics' joint commands (:class:`hilsim.services.physics.PhysicsService` sets these attributes)."""

    pending: list[tuple[int, World, msgs.JointState]]  # lockstep: (due step [ns], robot, command)
    robot_commands: bool  # whether the robots' own joint_commands are subscribed
    fleet_n: int  # joints per robot (robots as arrays)

    # ------------------------------------------------------------------ commands
    def _safe_commands(self, svc: str) -> None:
        """Realtime, the controller or the sensors it acts on gone: as a drive's command watchdog
        does, the simulated joints stop obeying the last command (a torque held for seconds would
        throw the arm about): effort joints get no torque, position joints hold where they are,
        velocity joints stop. The controller's next command, once both are back, replaces this."""
        for r in self.robots:
            js = r.world.joint_states()
            n = len(js.name)
            r.world.command(msgs.JointState(name=list(js.name), position=list(js.position),
                                            velocity=[0.0] * n, effort=[0.0] * n))
        self.log.info("%s gone: simulated joints without torque until commands come again", svc)

    def _apply(self, commands: list[tuple[World, msgs.JointState]], cmd: msgs.JointState,
               att: Attachment | None) -> None:
        """Apply ``commands`` (robot, its command), all from the sample ``cmd``, at the step they act on."""
        writer = att.gid.hex() if att is not None else None
        acks = [n for n, p in self.participants.items() if p.via == "joint_commands" and p.gid == writer]
        stamp = msgs.ns_of(cmd.header.stamp)
        if self.participants and self.started and not self.done:
            # lockstep: a command belongs to the step it answers and acts from that step + its
            # writer's lag (clock.controller_lag: the one-sample computation delay); one for
            # another step is stale (or not what it claims to be) and must not act on this one
            now = self.world.time_ns
            due = stamp + max((self.participants[n].lag for n in acks), default=0) * self.sc.dt_ns
            if due < now or stamp > now:
                raise msgs.BadMessage(f"command stamped t={stamp / 1e9:.3f}s, but the current step is "
                                      f"t={now / 1e9:.3f}s")
            if due > now:  # arrived before physics reached its step: acts there, whatever the timing
                self.pending.extend((due, w, c) for w, c in commands)
            else:
                for w, c in commands:
                    w.command(c)
        else:
            for w, c in commands:
                w.command(c)
        for name in acks:
            self._ack(name, stamp)

    def _subscribe_robot_commands(self) -> None:
        """Each robot's own joint_commands (the per-robot path: arrays off, or a robot's controller run
        alone, e.g. ``hilsim run controller@arm3``)."""
        self.robot_commands = True
        for r in self.robots:
            def on_command(cmd: msgs.JointState, key: str, att: Attachment | None, r: Robot = r) -> None:
                self._on_command(r.world, cmd, key, att)

            self.subscribe(r.keys.topic("joint_commands"), msgs.JointState, on_command, with_attachment=True)

    def _on_fleet_command(self, cmd: msgs.JointState, key: str, att: Attachment | None) -> None:
        """Every robot's command in one sample (joints ``<robot>/<joint>``): each robot's slice acts as its
        own joint_commands would; in lockstep it acknowledges the fleet driver's step for every robot."""
        if list(cmd.name) != self.fleet_names:
            raise msgs.BadMessage(f"fleet command names {len(cmd.name)} joints, not the fleet's "
                                  f"{len(self.fleet_names)} ({self.fleet_names[0]} …)")
        n = self.fleet_n
        cuts = [(r.world, slice(k * n, (k + 1) * n)) for k, r in enumerate(self.robots)]
        split = [(w, msgs.JointState(header=cmd.header, name=w.joint_names,
                                     position=cmd.position[c] if cmd.position else [],
                                     velocity=cmd.velocity[c] if cmd.velocity else [],
                                     effort=cmd.effort[c] if cmd.effort else []))
                 for w, c in cuts]
        self._apply(split, cmd, att)

    def _on_command(self, world: World, cmd: msgs.JointState, key: str, att: Attachment | None) -> None:
        self._apply([(world, cmd)], cmd, att)
