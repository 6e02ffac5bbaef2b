"""The MuJoCo world of a scenario, without any transport: load, command, step, read truth.

Each actuated joint has the command interface its scenario entry names (``joints.<name>``):
``effort`` (the motor torque), ``position`` or ``velocity`` (a simulated drive: MuJoCo's
affine servo, its force limited by the motor's effort limit). A joint served by an external
process (``server`` other than ``sim``) is not actuated: it *follows* the state its server
measured (:meth:`World.follow`), kinematically, so the links, contacts and the recording
stay consistent with the real motor.

A simulated joint with ``joints.<name>.drive`` is a servo drive simulated by physics in lockstep
(:mod:`hilsim.sim.drive`: dead time, closed position or velocity loop, velocity and acceleration
limits, the encoder's quantum and period), as ``hilsim identify`` fits it from a real drive: MuJoCo's
motor applies nothing, and the joint follows the drive's reported state kinematically after each
step, exactly as a joint served by that real drive follows its encoder.

A model whose root body has a free joint (a mobile robot such as the rover) also gets a
:class:`MobileBase`: its chassis pose and twist (``truth/odom``) and the transforms of the chassis
and its sensor sites (``tf``). A fixed-base model (the arm) has none, and nothing about it changes.

Used by the physics service and, unchanged, by the in-process baseline of ``hilsim bench loop``.
"""

from __future__ import annotations

import fnmatch
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

from hilsim.core import msgs
from hilsim.core.config import SIM, ConfigError, Scenario
from hilsim.sim.drive import DriveModel

SERVO_KP = {"position": 100.0, "velocity": 10.0}  # default drive gains [N·m/rad], [N·m·s/rad]
SERVO_KV = 5.0  # default damping of the position servos [N·m·s/rad]


class ModelError(ConfigError):
    """The world model cannot be used as the scenario asks (a configuration error)."""


def urdf_limits(urdf: Path) -> dict[str, tuple[float, float]]:
    """joint name -> (effort limit, velocity limit) from a URDF."""
    out: dict[str, tuple[float, float]] = {}
    for j in ET.parse(urdf).getroot().findall("joint"):  # not the <joint>s of <transmission> blocks
        lim = j.find("limit")
        if lim is not None and j.get("name"):
            out[j.get("name", "")] = (float(lim.get("effort", "inf")), float(lim.get("velocity", "inf")))
    return out


class World:
    """A compiled MuJoCo model with actuated joints addressed by name."""

    @staticmethod
    def load_spec(sc: Scenario) -> mujoco.MjSpec:
        """The scenario's world model as MuJoCo will compile it: the truth IMU's sensors added,
        gravity compensation set (a configuration error as one line)."""
        where = f"{sc.source}: " if sc.source else ""
        try:
            spec = mujoco.MjSpec.from_file(str(sc.world.model))
        except Exception as e:
            one_line = " ".join(str(e).split())
            raise ModelError(f"{where}world.model: cannot load {sc.world.model}: {one_line}") from e
        imu_site = sc.physics.truth_imu_site
        if imu_site:
            if not any(s.name == imu_site for s in spec.sites):
                raise ModelError(f"{where}physics.truth_imu_site: no site named {imu_site!r} in {sc.world.model}")
            # The IMU is emulated from MuJoCo's own sensors at the site (ground truth, no noise).
            for kind, name in ((mujoco.mjtSensor.mjSENS_ACCELEROMETER, "imu_acc"),
                               (mujoco.mjtSensor.mjSENS_GYRO, "imu_gyro"),
                               (mujoco.mjtSensor.mjSENS_FRAMEQUAT, "imu_quat")):
                s = spec.add_sensor(name=name, type=kind, objname=imu_site)
                s.objtype = mujoco.mjtObj.mjOBJ_SITE
        # As in the arm paper: link gravity off, inertia kept, for the bodies the scenario lists
        # (a wheeled base must keep its weight). Set before compiling: MuJoCo counts
        # gravity-compensated bodies at compile time.
        bodies = [b.name for b in spec.bodies if b.name != "world"]
        for pattern in sc.physics.gravity_compensation:
            hits = fnmatch.filter(bodies, pattern)
            if not hits:
                raise ModelError(f"{where}physics.gravity_compensation: no body matches {pattern!r} in "
                                 f"{sc.world.model} (bodies: {', '.join(bodies)})")
            for b in spec.bodies:
                if b.name in hits:
                    b.gravcomp = 1.0
        return spec

    def __init__(self, sc: Scenario, *, model: mujoco.MjModel | None = None, data: mujoco.MjData | None = None,
                 prefix: str = "") -> None:
        """The scenario's world; or, with ``model``, ``data`` and ``prefix``, one robot of a
        fleet's shared world (:class:`hilsim.sim.fleet_world.FleetWorld`): the actuators, joints and truth
        IMU whose names start with ``prefix``, addressed by their names without it."""
        self.sc = sc
        where = f"{sc.source}: " if sc.source else ""
        self.imu_site = sc.physics.truth_imu_site
        if model is None or data is None:
            model = self.load_spec(sc).compile()
            model.opt.timestep = sc.clock.dt
            data = mujoco.MjData(model)
        self.model, self.data, self.prefix = model, data, prefix
        m = self.model
        acts = [i for i in range(m.nu) if m.actuator(i).name.startswith(prefix)]
        if not acts:
            raise ModelError(f"{where}world.model: {sc.world.model} has no actuators")
        # a robot's actuators are contiguous (one attached copy): its slice of ctrl and forces
        self._act = slice(acts[0], acts[-1] + 1)
        assert acts == list(range(acts[0], acts[-1] + 1)), "a robot's actuators must be contiguous"
        nu = len(acts)
        self.actuators = [m.actuator(i).name[len(prefix):] for i in acts]
        self.joint_ids = [int(m.actuator_trnid[i, 0]) for i in acts]
        self.joint_names = [m.joint(j).name[len(prefix):] for j in self.joint_ids]
        self.qpos_adr = np.array([m.jnt_qposadr[j] for j in self.joint_ids])
        self.dof_adr = np.array([m.jnt_dofadr[j] for j in self.joint_ids])
        self._start_at_home(sc)
        self.effort_limit = np.array(
            [m.actuator_ctrlrange[i, 1] if m.actuator_ctrllimited[i] else math.inf for i in acts]
        )
        self.velocity_limit = np.full(nu, math.inf)
        if sc.world.urdf is not None:
            lim = urdf_limits(sc.world.urdf)
            for i, n in enumerate(self.joint_names):
                if n in lim:
                    self.velocity_limit[i] = lim[n][1]
        for jname in sc.joints:
            if jname != "default" and jname not in self.joint_names:
                raise ModelError(f"{where}joints.{jname}: no actuated joint of that name in {sc.world.model} "
                                 f"(joints: {', '.join(self.joint_names)})")
        cfg = [sc.joint(n) for n in self.joint_names]
        self.interfaces = [c.interface for c in cfg]
        self.servers = [c.server for c in cfg]
        self.external = np.array([s != SIM for s in self.servers])
        self.ext_index = [i for i, e in enumerate(self.external) if e]
        self._servo_kp = np.zeros(nu)
        self._servo_kv = np.zeros(nu)
        # simulated drives (joints.<name>.drive), by actuator index: stepped here, followed like a real drive
        self._drive_at: dict[int, DriveModel] = {}
        for i, c in enumerate(cfg):
            if c.server == SIM and c.drive is not None:
                p0 = float(self.data.qpos[self.qpos_adr[i]])
                self._drive_at[i] = DriveModel(c.drive, p0, velocity_mode=c.interface == "velocity")
            elif c.server == SIM and c.interface != "effort":
                self._make_servo(i, c.interface, c.servo_kp or SERVO_KP[c.interface],
                                 SERVO_KV if c.servo_kv is None else c.servo_kv)
        # an external joint's motor is real, a simulated drive's is its model: MuJoCo's applies nothing
        for i in [*self.ext_index, *self._drive_at]:
            m.actuator_gainprm[acts[i], 0] = 0.0
            m.actuator_biasprm[acts[i], :3] = 0.0
        self._effort = np.array([c.interface == "effort" and c.server == SIM for c in cfg])
        self._all_effort = bool(self._effort.all())
        # the lean path of apply_commands: a handful of joints is cheaper as Python floats than as
        # numpy calls on tiny arrays (about 1 µs against 4.5 per step)
        self._limits = list(zip(self.effort_limit.tolist(), self.velocity_limit.tolist(), strict=True))
        # a robot's joints are usually contiguous in the model: then a slice, cheaper than an index array
        self._dof, self._qpos = _span(self.dof_adr), _span(self.qpos_adr)
        self.index = {n: i for i, n in enumerate(self.joint_names)}
        ff_gain = [kv / kp if f == "position" and kp else 0.0
                   for f, kp, kv in zip(self.interfaces, self._servo_kp, self._servo_kv, strict=True)]
        # per joint name: (actuator index, interface or None when served externally, feed-forward gain)
        self._how = {n: (i, None if self.external[i] else self.interfaces[i], ff_gain[i])
                     for n, i in self.index.items()}
        self._cmd = np.zeros(nu)
        self.clipped = 0  # effort commands beyond the joint's limit (applied at the limit)
        # external joints: the latest measured (position, velocity) from their server
        self._follow_pos = np.zeros(len(self.ext_index))
        self._follow_vel = np.zeros(len(self.ext_index))
        self._follow_ok = np.zeros(len(self.ext_index), dtype=bool)
        self._follow_t = np.zeros(len(self.ext_index), dtype=np.int64)  # sim time of the report
        self._extrapolate_ns = round(sc.physics.follow_extrapolation * 1e9)
        if self.imu_site:
            self._acc = m.sensor(f"{prefix}imu_acc").adr[0]
            self._gyro = m.sensor(f"{prefix}imu_gyro").adr[0]
            self._quat = m.sensor(f"{prefix}imu_quat").adr[0]
        self.step_index = 0
        self._dt_ns = sc.dt_ns  # read every step: the scenario's property computes it
        self.base = MobileBase.of(m, self.data)  # None for a fixed-base robot
        self._mine: np.ndarray | None = None  # a fleet's robot: which geoms are its own (its cell's)
        if prefix:
            if self.base is not None:
                raise ModelError(f"{where}robots: {sc.robots} copies of a mobile robot are not supported "
                                 f"(only fixed-base robots, such as the arm)")
            self._mine = np.array([
                (m.body(int(m.geom_bodyid[g])).name if m.geom_bodyid[g] else m.geom(g).name).startswith(prefix)
                for g in range(m.ngeom)])
        mujoco.mj_forward(m, self.data)

    def _start_at_home(self, sc: Scenario) -> None:
        """Start where the scenario says (``world.home``), else at the model's keyframe ``home`` (a
        fleet's copy: ``<robot>/home``), else at the model's zero pose."""
        m, d = self.model, self.data
        k = next((i for i in range(m.nkey) if m.key(i).name in (f"{self.prefix}home", "home")), None)
        if k is not None:
            if self.prefix:  # a shared world: this robot's joints only
                d.qpos[self.qpos_adr] = m.key_qpos[k][self.qpos_adr]
            else:  # the whole key: mimic joints and anything else the model poses there too
                mujoco.mj_resetDataKeyframe(m, d, k)
        if sc.world.home is not None:
            d.qpos[self.qpos_adr] = sc.world.home
        if k is not None or sc.world.home is not None:
            mujoco.mj_forward(m, d)

    def _make_servo(self, i: int, interface: str, kp: float, kv: float) -> None:
        """Turn motor ``i`` into a position or velocity servo (MuJoCo's affine actuator form:
        force = kp·ctrl − kp·q − kv·q̇, solved implicitly, so stiff gains stay stable at 1 kHz)."""
        m, k, i = self.model, i, self._act.start + i  # k: this robot's motor, i: the model's
        m.actuator_gaintype[i] = mujoco.mjtGain.mjGAIN_FIXED
        m.actuator_biastype[i] = mujoco.mjtBias.mjBIAS_AFFINE
        m.actuator_gainprm[i, 0] = kp
        # a position servo needs damping, or it rings around its setpoint
        m.actuator_biasprm[i, :3] = (0.0, -kp, -kv) if interface == "position" else (0.0, 0.0, -kp)
        # the command is now a setpoint; the effort limit moves to the force range
        m.actuator_forcelimited[i] = 1
        m.actuator_forcerange[i] = (-self.effort_limit[k], self.effort_limit[k])
        m.actuator_ctrllimited[i] = 0
        self._servo_kp[k], self._servo_kv[k] = kp, kv

    @property
    def time_ns(self) -> int:
        return self.step_index * self._dt_ns

    def command(self, cmd: msgs.JointState) -> None:
        """Take a joint command by name. It may name any subset of the joints (the others keep
        their last command); each simulated joint reads the field of its interface (a position
        joint also its ``velocity``, as feed-forward, when given); external joints are skipped:
        their server reads the same message. All-or-nothing: a bad entry changes nothing."""
        n = len(cmd.name)
        if self._all_effort and len(cmd.effort) == n and cmd.name == self.joint_names:
            # the controller's every step: every joint's effort, in the model's order
            self._cmd[:] = cmd.effort
            for v, (lim, _) in zip(cmd.effort, self._limits, strict=True):
                if v > lim or v < -lim:
                    self.clipped += 1  # applied at the limit (in step), and counted: never silently
            return
        fields = {"effort": cmd.effort, "position": cmd.position, "velocity": cmd.velocity}
        ff = cmd.velocity if len(cmd.velocity) == n else None
        new: list[tuple[int, float]] = []
        to_drives: list[tuple[DriveModel, float, float]] = []
        for k, jn in enumerate(cmd.name):
            how = self._how.get(jn)  # (actuator index, interface or None if external, feed-forward gain)
            if how is None:
                raise msgs.BadMessage(f"joint command names unknown joint {jn!r}")
            i, iface, gain = how
            if iface is None:
                continue
            values = fields[iface]
            if len(values) != n:
                raise msgs.BadMessage(f"joint command has no {iface} values for joint {jn!r} ({iface} interface)")
            drive = self._drive_at.get(i) if self._drive_at else None
            if drive is not None:  # a simulated drive: the setpoint with its velocity feed-forward, as a real one
                if iface == "position":
                    to_drives.append((drive, values[k], ff[k] if ff is not None else 0.0))
                else:
                    to_drives.append((drive, drive.p_in, values[k]))
                continue
            # position joints: velocity feed-forward through the affine servo, kp·(p + kv/kp·v) − kp·q − kv·q̇
            new.append((i, values[k] + gain * ff[k] if gain and ff is not None else values[k]))
        c, lim = self._cmd, self.effort_limit
        for i, v in new:
            c[i] = v
            if self._effort[i] and abs(v) > lim[i]:
                self.clipped += 1  # applied at the limit (in step), and counted: never silently
        if to_drives:
            stamp = msgs.ns_of(cmd.header.stamp) * 1e-9  # the drive acts its dead time after the command's stamp
            for drive, p_in, v_in in to_drives:
                drive.command(stamp, p_in, v_in)

    def command_array(self, u: np.ndarray) -> None:
        self._cmd[:] = u

    def follow(self, names: list[str], position: list[float], velocity: list[float]) -> None:
        """The measured state of external joints, from their server; applied from the next step."""
        for k, jn in enumerate(names):
            i = self.index.get(jn)
            if i is None or not self.external[i]:
                raise msgs.BadMessage(f"joint {jn!r} is not served externally in this scenario")
            e = self.ext_index.index(i)
            self._follow_pos[e] = position[k]
            self._follow_vel[e] = velocity[k] if velocity else 0.0
            self._follow_ok[e] = True
            self._follow_t[e] = self.time_ns

    def hold(self, names: list[str]) -> None:
        """External joints whose server went silent: keep the last measured position, at rest."""
        for jn in names:
            self._follow_vel[self.ext_index.index(self.index[jn])] = 0.0

    def step(self) -> None:
        self.apply_commands()
        mujoco.mj_step(self.model, self.data)
        self.after_step()

    def apply_commands(self) -> None:
        """The motors' inputs for the next step (limits applied). A fleet's world calls this for
        each robot, steps once, then :meth:`after_step` for each."""
        if self._all_effort:  # the common case, kept lean: every joint a simulated effort joint
            u = []
            for x, (lim, vlim), v in zip(self._cmd.tolist(), self._limits, self.data.qvel[self._dof].tolist(),
                                         strict=True):
                x = lim if x > lim else -lim if x < -lim else x
                # velocity limit as a drive enforces it: no torque that pushes further past the limit
                u.append(0.0 if (v > vlim or v < -vlim) and x * v > 0.0 else x)
            self.data.ctrl[self._act] = u
            return
        u = np.where(self._effort, np.clip(self._cmd, -self.effort_limit, self.effort_limit), self._cmd)
        v = self.data.qvel[self.dof_adr]
        over = (np.abs(v) > self.velocity_limit) & (np.sign(u) == np.sign(v)) & self._effort
        if over.any():
            u = np.where(over, 0.0, u)
        self.data.ctrl[self._act] = u

    def after_step(self) -> None:
        if self.ext_index:
            self._apply_follow()
        if self._drive_at:
            self._apply_drives()
        self.step_index += 1

    def _apply_drives(self) -> None:
        """Simulated drives: each moved on to the end of this step, its joint put where its encoder
        reports it (as a joint served by a real drive is), after integrating."""
        d, t = self.data, (self.step_index + 1) * self._dt_ns * 1e-9
        for i, drive in self._drive_at.items():
            drive.advance(t)
            d.qpos[self.qpos_adr[i]] = drive.out_p
            d.qvel[self.dof_adr[i]] = drive.out_v

    def _apply_follow(self) -> None:
        """Kinematic follow: overwrite the external joints' state with their server's latest
        measurement after integrating, so the next step's contacts and truth see the real motor.
        Until a server has reported, its joint is held where it is."""
        d = self.data
        for e, i in enumerate(self.ext_index):
            if self._follow_ok[e]:
                pos = self._follow_pos[e]
                if self._extrapolate_ns:
                    # a drive that reports every 10 ms would move the link in steps: carry the
                    # last report forward at its velocity, for at most physics.follow_extrapolation
                    age = min(self.time_ns - self._follow_t[e], self._extrapolate_ns)
                    pos += self._follow_vel[e] * age * 1e-9
                d.qpos[self.qpos_adr[i]] = pos
                d.qvel[self.dof_adr[i]] = self._follow_vel[e]
            else:
                d.qpos[self.qpos_adr[i]] -= d.qvel[self.dof_adr[i]] * self.sc.clock.dt
                d.qvel[self.dof_adr[i]] = 0.0

    def positions(self) -> np.ndarray:
        return self.data.qpos[self.qpos_adr].copy()

    def velocities(self) -> np.ndarray:
        return self.data.qvel[self.dof_adr].copy()

    def contact_pairs(self) -> frozenset[tuple[int, int]]:
        """The geom pairs in contact now (cheap: compared every step to publish changes only)."""
        d = self.data
        if not d.ncon:
            return frozenset()
        pairs = zip(d.contact.geom1[: d.ncon].tolist(), d.contact.geom2[: d.ncon].tolist(), strict=True)
        if self._mine is not None:  # a fleet's robot: the contacts in its own cell
            return frozenset(p for p in pairs if self._mine[p[0]] or self._mine[p[1]])
        return frozenset(pairs)

    def contacts(self) -> msgs.Contacts:
        """Every contact now, with its bodies' and geoms' names (unnamed geoms: ``geom<id>``)."""
        m, d = self.model, self.data
        out = []
        n = len(self.prefix)  # a fleet's robot: its names as in the single robot's world

        def own(name: str) -> str:
            return name[n:] if n and name.startswith(self.prefix) else name

        for c in d.contact[: d.ncon]:
            g1, g2 = int(c.geom1), int(c.geom2)
            if self._mine is not None and not (self._mine[g1] or self._mine[g2]):
                continue
            out.append(msgs.Contact(
                body1=own(m.body(int(m.geom_bodyid[g1])).name), body2=own(m.body(int(m.geom_bodyid[g2])).name),
                geom1=own(m.geom(g1).name) or f"geom{g1}", geom2=own(m.geom(g2).name) or f"geom{g2}",
                position=msgs.Point(x=float(c.pos[0]), y=float(c.pos[1]), z=float(c.pos[2])),
                depth=-float(c.dist),
            ))
        return msgs.Contacts(header=msgs.header(self.time_ns, "world"), contacts=out)

    def joint_states(self) -> msgs.JointState:
        d = self.data
        return msgs.JointState(
            header=msgs.header(self.time_ns, "world"),
            name=self.joint_names,
            position=d.qpos[self._qpos].tolist(),
            velocity=d.qvel[self._dof].tolist(),
            effort=d.actuator_force[self._act].tolist(),
        )

    def imu(self) -> msgs.Imu | None:
        if not self.imu_site:
            return None
        s = self.data.sensordata
        a, g = s[self._acc:self._acc + 3].tolist(), s[self._gyro:self._gyro + 3].tolist()
        q = s[self._quat:self._quat + 4].tolist()
        return msgs.Imu(
            header=msgs.header(self.time_ns, self.imu_site),
            orientation=msgs.Quaternion(x=q[1], y=q[2], z=q[3], w=q[0]),
            angular_velocity=msgs.Vector3(x=g[0], y=g[1], z=g[2]),
            linear_acceleration=msgs.Vector3(x=a[0], y=a[1], z=a[2]),
        )


def _span(adr: np.ndarray) -> slice | np.ndarray:
    """``adr`` as a slice when its addresses are consecutive, else itself (both index the same entries)."""
    a = adr.tolist()
    return slice(a[0], a[-1] + 1) if a and a == list(range(a[0], a[0] + len(a))) else adr


class MobileBase:
    """Ground truth of a free-floating base: the body of the model's free joint (the chassis).

    ``odometry`` is nav_msgs/Odometry of the chassis in the world frame (``header.frame_id``
    ``world``, ``child_frame_id`` the chassis body): pose = the free joint's position and
    orientation, twist in the chassis frame (ROS convention: linear and angular velocity of the
    body expressed in ``child_frame_id``). ``transforms`` is tf2_msgs/TFMessage: world → chassis,
    then chassis → each site on the chassis (the sensor frames, e.g. ``laser``, ``imu``, ``gps``).
    """

    def __init__(self, m: mujoco.MjModel, d: mujoco.MjData, joint: int) -> None:
        self.m, self.d = m, d
        self.body = int(m.jnt_bodyid[joint])
        self.name = m.body(self.body).name
        self.qadr = int(m.jnt_qposadr[joint])
        self.sites = [(m.site(i).name, m.site_pos[i].copy(), m.site_quat[i].copy())
                      for i in range(m.nsite) if m.site_bodyid[i] == self.body]
        self._vel = np.zeros(6)

    @classmethod
    def of(cls, m: mujoco.MjModel, d: mujoco.MjData) -> MobileBase | None:
        """The mobile base of a model: the first free joint whose body hangs from the world."""
        for j in range(m.njnt):
            if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE and m.body_parentid[m.jnt_bodyid[j]] == 0:
                return cls(m, d, j)
        return None

    def odometry(self, stamp_ns: int) -> msgs.Odometry:
        q = self.d.qpos[self.qadr:self.qadr + 7]
        # XBODY: the body frame (BODY would be its principal inertia frame)
        mujoco.mj_objectVelocity(self.m, self.d, mujoco.mjtObj.mjOBJ_XBODY, self.body, self._vel, 1)
        w, v = self._vel[:3], self._vel[3:]
        return msgs.Odometry(
            header=msgs.header(stamp_ns, "world"),
            child_frame_id=self.name,
            pose=msgs.PoseWithCovariance(pose=msgs.Pose(
                position=msgs.Point(x=float(q[0]), y=float(q[1]), z=float(q[2])),
                orientation=msgs.Quaternion(x=float(q[4]), y=float(q[5]), z=float(q[6]), w=float(q[3])))),
            twist=msgs.TwistWithCovariance(twist=msgs.Twist(
                linear=msgs.Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2])),
                angular=msgs.Vector3(x=float(w[0]), y=float(w[1]), z=float(w[2])))),
        )

    def transforms(self, stamp_ns: int) -> msgs.TFMessage:
        q = self.d.qpos[self.qadr:self.qadr + 7]
        out = [msgs.TransformStamped(
            header=msgs.header(stamp_ns, "world"), child_frame_id=self.name,
            transform=msgs.Transform(
                translation=msgs.Vector3(x=float(q[0]), y=float(q[1]), z=float(q[2])),
                rotation=msgs.Quaternion(x=float(q[4]), y=float(q[5]), z=float(q[6]), w=float(q[3]))))]
        for name, pos, quat in self.sites:
            out.append(msgs.TransformStamped(
                header=msgs.header(stamp_ns, self.name), child_frame_id=name,
                transform=msgs.Transform(
                    translation=msgs.Vector3(x=float(pos[0]), y=float(pos[1]), z=float(pos[2])),
                    rotation=msgs.Quaternion(x=float(quat[1]), y=float(quat[2]), z=float(quat[3]),
                                             w=float(quat[0])))))
        return msgs.TFMessage(transforms=out)
