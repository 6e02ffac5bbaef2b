"""Physics' truth: each robot's truth publishers, and what physics writes after every step.

A part of :class:`hilsim.services.physics.PhysicsService` (one of its bases, not a service of its own).
:class:`Robot` is one robot's part of the world (a fleet has one per robot) with its publishers;
:meth:`PhysicsTruth._publish_step` writes the step's truth, each robot's ``truth/joint_states`` last
(see docs/keys.md), then the clock.

Writes (stamped with the step's sim time): ``<prefix>/<robot>/truth/imu``, ``truth/odom`` and ``/tf``
(mobile robots), ``/tf`` at ``physics.tf_rate_hz`` (the URDF's moving joints), ``/tf_static`` and
``<ns>/robot_description`` (once, transient-local), ``truth/contacts`` (when the set of touching geom
pairs changes), ``truth/joint_states``, ``fleet/truth/joint_states`` (robots as arrays) and
``<prefix>/clock``.
"""

from __future__ import annotations

import numpy as np

from hilsim.core import msgs
from hilsim.core.keys import Keys
from hilsim.core.service import Publisher, Service
from hilsim.sim.fleet_world import FleetWorld
from hilsim.sim.tf import UrdfFrames
from hilsim.sim.world import World


class Robot:
    """One robot's part of the world and its truth publishers (a fleet has one per robot)."""

    def __init__(self, svc: Service, keys: Keys, world: World, fleet_robot: str | None = None) -> None:
        self.keys, self.world = keys, world
        self.pub_imu = svc.publisher(keys.truth("imu")) if world.imu_site else None
        # a mobile base (free joint) also has truth/odom; its pose in the world goes on /tf every step
        self.pub_odom = svc.publisher(keys.truth("odom")) if world.base else None
        # the URDF's frames (robot_state_publisher's job): fixed joints once on /tf_static, moving ones
        # on /tf at physics.tf_rate_hz, the URDF itself on robot_description (both transient-local)
        urdf = svc.sc.world.urdf
        self.frames = UrdfFrames(urdf, f"{fleet_robot}/" if fleet_robot else "") if urdf is not None else None
        self.pub_tf = svc.publisher(keys.tf) if world.base or self.frames else None
        if self.frames is not None:
            svc.publisher(keys.tf_static, latched=True).put(self.frames.static(world.time_ns))
            svc.publisher(keys.topic("robot_description"), latched=True).put(msgs.String(data=self.frames.urdf_text))
        self.pub_js = svc.publisher(keys.truth("joint_states"))
        # contacts: published when the set of touching geom pairs changes (and once at start), so
        # every contact is in the record without a message per step
        self.pub_contacts: Publisher = svc.publisher(keys.truth("contacts"))
        self.contact_pairs: frozenset[tuple[int, int]] | None = None


class PhysicsTruth(Service):
    """Physics' truth out (:class:`hilsim.services.physics.PhysicsService` sets these attributes)."""

    world: World | FleetWorld
    robots: list[Robot]
    tf_period: int  # steps between the URDF's moving frames on /tf (0: never)
    contact_steps: int  # steps with a contact
    arrays: bool  # robots as arrays (hilsim.core.fleet)
    fleet_names: list[str]
    pub_fleet_js: Publisher
    pub_clock: Publisher
    _fq: np.ndarray  # every robot's joints' qpos, qvel and actuator addresses, in fleet order
    _fv: np.ndarray
    _fa: np.ndarray

    # ------------------------------------------------------------------ stepping
    def _publish_step(self) -> None:
        self.sim_ns = self.world.time_ns
        for r in self.robots:  # each robot's truth, its truth/joint_states last (see docs/keys.md)
            w = r.world
            if r.pub_imu is not None:
                imu = w.imu()
                assert imu is not None
                r.pub_imu.put(imu)
            if w.base is not None and r.pub_odom is not None and r.pub_tf is not None:
                # before truth/joint_states: the sensors' step is complete once they handled that one
                r.pub_odom.put(w.base.odometry(w.time_ns))
                r.pub_tf.put(w.base.transforms(w.time_ns))
            if r.frames is not None and self.tf_period and w.step_index % self.tf_period == 0:
                assert r.pub_tf is not None
                q = dict(zip(w.joint_names, w.positions().tolist(), strict=True))
                r.pub_tf.put(msgs.TFMessage(transforms=r.frames.moving_transforms(w.time_ns, q)))
            if w.data.ncon or r.contact_pairs:  # the arm: nothing to look at on almost every step
                pairs = w.contact_pairs()
                self.contact_steps += bool(pairs)
                if pairs != r.contact_pairs:
                    r.contact_pairs = pairs
                    r.pub_contacts.put(w.contacts())
            elif r.contact_pairs is None:
                r.contact_pairs = frozenset()
                r.pub_contacts.put(w.contacts())
            if not self.arrays or r.pub_js.wanted(covered=True):  # arrays: the fleet sample carries it anyway
                r.pub_js.put(w.joint_states())
            else:
                r.pub_js.skip()
        if self.arrays:
            if self.pub_fleet_js.wanted():
                d = self.world.data
                self.pub_fleet_js.put(msgs.JointState(
                    header=msgs.header(self.world.time_ns, "world"), name=self.fleet_names,
                    position=d.qpos[self._fq].tolist(), velocity=d.qvel[self._fv].tolist(),
                    effort=d.actuator_force[self._fa].tolist()))
            else:
                self.pub_fleet_js.skip()
        self.pub_clock.put(msgs.Clock(clock=msgs.stamp(self.world.time_ns)))
