"""The MuJoCo world of a scenario, without any transport: load, command, step, read truth.

Used by the physics service and, unchanged, by the in-process baseline of ``hilsim bench loop``.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

from hilsim import msgs
from hilsim.config import ConfigError, Scenario

SERVO_KV = 5.0  # damping of the position servos [N·m·s/rad]


class ModelError(ConfigError):
    """The world model cannot be used as the scenario asks (a configuration error)."""


def urdf_limits(urdf: Path) -> dict[str, tuple[float, float]]:
    """joint name -> (effort limit, velocity limit) from a URDF."""
    out: dict[str, tuple[float, float]] = {}
    for j in ET.parse(urdf).getroot().iter("joint"):
        lim = j.find("limit")
        if lim is not None and j.get("name"):
            out[j.get("name", "")] = (float(lim.get("effort", "inf")), float(lim.get("velocity", "inf")))
    return out


class World:
    """A compiled MuJoCo model with actuated joints addressed by name."""

    def __init__(self, sc: Scenario) -> None:
        self.sc = sc
        where = f"{sc.source}: " if sc.source else ""
        try:
            spec = mujoco.MjSpec.from_file(str(sc.world.model))
        except Exception as e:
            one_line = " ".join(str(e).split())
            raise ModelError(f"{where}world.model: cannot load {sc.world.model}: {one_line}") from e
        self.imu_site = sc.physics.truth_imu_site
        if self.imu_site:
            if not any(s.name == self.imu_site for s in spec.sites):
                raise ModelError(f"{where}physics.truth_imu_site: no site named {self.imu_site!r} in {sc.world.model}")
            # The IMU is emulated from MuJoCo's own sensors at the site (ground truth, no noise).
            for kind, name in ((mujoco.mjtSensor.mjSENS_ACCELEROMETER, "imu_acc"),
                               (mujoco.mjtSensor.mjSENS_GYRO, "imu_gyro"),
                               (mujoco.mjtSensor.mjSENS_FRAMEQUAT, "imu_quat")):
                s = spec.add_sensor(name=name, type=kind, objname=self.imu_site)
                s.objtype = mujoco.mjtObj.mjOBJ_SITE
        if sc.world.gravity_compensation:
            # As in the arm paper: link gravity off, inertia kept. Set before compiling:
            # MuJoCo counts gravity-compensated bodies at compile time.
            for b in spec.bodies:
                b.gravcomp = 1.0
        self.model = spec.compile()
        self.model.opt.timestep = sc.clock.dt
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.actuators = [m.actuator(i).name for i in range(m.nu)]
        if not self.actuators:
            raise ModelError(f"{where}world.model: {sc.world.model} has no actuators")
        self.joint_ids = [int(m.actuator_trnid[i, 0]) for i in range(m.nu)]
        self.joint_names = [m.joint(j).name for j in self.joint_ids]
        self.qpos_adr = np.array([m.jnt_qposadr[j] for j in self.joint_ids])
        self.dof_adr = np.array([m.jnt_dofadr[j] for j in self.joint_ids])
        self.effort_limit = np.array(
            [m.actuator_ctrlrange[i, 1] if m.actuator_ctrllimited[i] else math.inf for i in range(m.nu)]
        )
        self.velocity_limit = np.full(m.nu, math.inf)
        if sc.world.urdf is not None:
            lim = urdf_limits(sc.world.urdf)
            for i, n in enumerate(self.joint_names):
                if n in lim:
                    self.velocity_limit[i] = lim[n][1]
        self.mode = sc.physics.actuator
        if self.mode != "effort":
            self._make_servos()
        self.index = {n: i for i, n in enumerate(self.joint_names)}
        self._cmd = np.zeros(m.nu)
        if self.imu_site:
            self._acc = m.sensor("imu_acc").adr[0]
            self._gyro = m.sensor("imu_gyro").adr[0]
            self._quat = m.sensor("imu_quat").adr[0]
        self.step_index = 0
        mujoco.mj_forward(m, self.data)

    def _make_servos(self) -> None:
        """Turn the motors into position or velocity servos (MuJoCo's affine actuator form)."""
        m = self.model
        for i in range(m.nu):
            kp = 100.0 if self.mode == "position" else 10.0
            m.actuator_gaintype[i] = mujoco.mjtGain.mjGAIN_FIXED
            m.actuator_biastype[i] = mujoco.mjtBias.mjBIAS_AFFINE
            m.actuator_gainprm[i, 0] = kp
            # a position servo needs damping, or it rings around its setpoint
            m.actuator_biasprm[i, :3] = (0.0, -kp, -SERVO_KV) if self.mode == "position" else (0.0, 0.0, -kp)
            # the command is now a setpoint; the effort limit moves to the force range
            m.actuator_forcelimited[i] = 1
            m.actuator_forcerange[i] = (-self.effort_limit[i], self.effort_limit[i])
            m.actuator_ctrllimited[i] = 0

    @property
    def time_ns(self) -> int:
        return self.step_index * self.sc.dt_ns

    def command(self, cmd: msgs.JointState) -> None:
        """Take a joint command (by name); fields used depend on the actuator mode."""
        values = {"effort": cmd.effort, "position": cmd.position, "velocity": cmd.velocity}[self.mode]
        if len(values) != len(cmd.name):
            raise msgs.BadMessage(f"joint command has no {self.mode} values for its {len(cmd.name)} joints")
        for n, v in zip(cmd.name, values, strict=True):
            i = self.index.get(n)
            if i is None:
                raise msgs.BadMessage(f"joint command names unknown joint {n!r}")
            self._cmd[i] = v

    def command_array(self, u: np.ndarray) -> None:
        self._cmd[:] = u

    def step(self) -> None:
        u = self._cmd
        if self.mode == "effort":
            u = np.clip(u, -self.effort_limit, self.effort_limit)
            # velocity limit as a drive enforces it: no torque that pushes further past the limit
            v = self.data.qvel[self.dof_adr]
            over = (np.abs(v) > self.velocity_limit) & (np.sign(u) == np.sign(v))
            if over.any():
                u = np.where(over, 0.0, u)
        self.data.ctrl[:] = u
        mujoco.mj_step(self.model, self.data)
        self.step_index += 1

    def positions(self) -> np.ndarray:
        return self.data.qpos[self.qpos_adr].copy()

    def velocities(self) -> np.ndarray:
        return self.data.qvel[self.dof_adr].copy()

    def joint_states(self) -> msgs.JointState:
        d = self.data
        return msgs.JointState(
            header=msgs.header(self.time_ns, "world"),
            name=self.joint_names,
            position=d.qpos[self.qpos_adr].tolist(),
            velocity=d.qvel[self.dof_adr].tolist(),
            effort=d.actuator_force.tolist(),
        )

    def imu(self) -> msgs.Imu | None:
        if not self.imu_site:
            return None
        s = self.data.sensordata
        a, g, q = s[self._acc:self._acc + 3], s[self._gyro:self._gyro + 3], s[self._quat:self._quat + 4]
        return msgs.Imu(
            header=msgs.header(self.time_ns, self.imu_site),
            orientation=msgs.Quaternion(x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])),
            angular_velocity=msgs.Vector3(x=float(g[0]), y=float(g[1]), z=float(g[2])),
            linear_acceleration=msgs.Vector3(x=float(a[0]), y=float(a[1]), z=float(a[2])),
        )
