"""The ``four_wheel_steer`` controller: the rover's intermediate layer, from body twist to wheel torques.

As in the thesis: a kinematic layer turns a body velocity (geometry_msgs/Twist on ``cmd_vel``) into
each wheel's steering angle and traction speed (:mod:`hilsim.sim.steering`: Ackermann-like with both
axles in opposite phase, crab, turn in place; a wheel is reversed rather than steered past its
limit), and one PID per wheel and motor closes the steering-angle and the traction-speed loop
(gains ``controller.gains.steering`` / ``.traction``, or per joint name, falling back to ``default``).
Wheel odometry (the least-squares body twist of the measured wheel angles and speeds, with the
yaw rate of the IMU's gyro when ``params.imu_yaw_rate``, integrated) is published on ``odom``.
It is the lockstep participant like the arm's controller: its ``joint_commands`` of a step is
its acknowledgement.

Reads (``<prefix>/<robot>/…``):
  ``joint_states`` (sensor_msgs/JointState, measured; one control step per message),
  ``imu`` (sensor_msgs/Imu: the gyro's yaw rate for the odometry, unless ``params.imu_yaw_rate: false``;
  in lockstep a control step whose imu is due waits for it, so the odometry is reproducible),
  ``cmd_vel`` (geometry_msgs/Twist: linear.x, linear.y [m/s], angular.z [rad/s] in base_link; held
  for ``params.cmd_timeout`` sim seconds, then the rover stops; in lockstep with the navigator,
  which sends one per decision step, a control step waits for those of the steps before it).
Writes:
  ``joint_commands`` (sensor_msgs/JointState) stamped like the joint_states it answers, every joint,
  all three fields: ``position`` = steering angle reference (traction joints: the integrated
  speed reference), ``velocity`` = traction speed reference (steering joints: 0, or for a
  velocity-interface one ``controller.velocity_gain·(angle_ref − angle)``), ``effort`` = the
  PID output for effort joints (0 for the others, whose server closes the loop itself);
  ``odom`` (nav_msgs/Odometry, frame ``odom`` → ``base_link``, twist in base_link) at every control step.
Serves:
  ``controller/set_parameters`` (``<joint>.<kp|ki|kd|i_limit|output_limit|feedforward>``), live.

Settings (``controller.params``): ``max_speed`` [m/s], ``max_yaw_rate`` [rad/s], ``cmd_timeout``
[sim s], ``wheels`` (names: joints ``<w>_steering`` and ``<w>_traction``), ``script`` (a list of
``[t, vx, vy, wz]``: the twist from sim time ``t`` on, used while no fresh ``cmd_vel`` overrides it,
so a run can be scripted and reproducible; a navigation layer would publish ``cmd_vel`` instead).
"""

from __future__ import annotations

import itertools
import math
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from hilsim.core import msgs
from hilsim.core.config import ConfigError, PidGains, Scenario, format_error
from hilsim.core.service import Publisher, Service
from hilsim.sim import control, steering
from hilsim.sim.world import urdf_limits


class FourWheelSteerParams(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    max_speed: float = Field(1.0, gt=0, description="body speed limit [m/s]")
    max_yaw_rate: float = Field(1.5, gt=0, description="[rad/s]")
    cmd_timeout: float = Field(0.5, gt=0, description="sim seconds a cmd_vel is held")
    wheels: list[str] = Field(default_factory=lambda: ["fl", "fr", "rl", "rr"])
    imu_yaw_rate: bool = Field(True, description="odometry takes its yaw rate from the imu (gyro z; the imu "
                               "frame is the chassis') when one of this control step is there, else the wheels")
    script: list[tuple[float, float, float, float]] = Field(
        default_factory=list, description="[t, vx, vy, wz] from sim time t on (until a fresh cmd_vel)")

    @field_validator("script")
    @classmethod
    def _sorted(cls, v: list[tuple[float, float, float, float]]) -> list[tuple[float, float, float, float]]:
        if any(b[0] < a[0] for a, b in itertools.pairwise(v)):
            raise ValueError("script times must not decrease")
        return v


def wheel_geometry(model_path: Any, wheels: list[str], where: str = "") -> tuple[steering.Geometry, list[str],
                                                                                  list[str]]:
    """Wheel positions (steering axes in the chassis frame), radius and steering limits of a
    model, and the names of its steering and traction joints."""
    import mujoco

    m = mujoco.MjModel.from_xml_path(str(model_path))
    joints = [m.joint(j).name for j in range(m.njnt)]
    steer = [f"{w}_steering" for w in wheels]
    drive = [f"{w}_traction" for w in wheels]
    for n in steer + drive:
        if n not in joints:
            raise ConfigError(f"{where}controller.params.wheels: no joint {n!r} in {model_path} "
                              f"(joints: {', '.join(joints)})")
    pos, radii, lo, hi = [], [], [], []
    for s, d in zip(steer, drive, strict=True):
        js, jd = m.joint(s), m.joint(d)
        p = m.body_pos[js.bodyid[0]]
        pos.append((float(p[0]), float(p[1])))
        wheel_body = jd.bodyid[0]
        geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] == wheel_body]
        if not geoms:
            raise ConfigError(f"{where}controller.params.wheels: {d} moves no geom (no wheel radius)")
        radii.append(float(m.geom_size[geoms[0], 0]))
        lo.append(float(m.jnt_range[js.id, 0]) if js.limited[0] else -math.pi)
        hi.append(float(m.jnt_range[js.id, 1]) if js.limited[0] else math.pi)
    return steering.Geometry(tuple(pos), float(np.mean(radii)), max(lo), min(hi)), steer, drive


class FourWheelSteerController(Service):
    """``controller.type: four_wheel_steer`` (see the module doc)."""

    name: ClassVar[str] = "controller"
    stop_rank: ClassVar[int] = 20
    ack_via: ClassVar[str] = "joint_commands"
    writes_topics: ClassVar[tuple[str, ...]] = ("joint_commands", "odom")  # e.g. what a ROS 2 bridge offers

    @classmethod
    def lockstep_period(cls, sc: Scenario) -> int | None:
        return sc.control_decimation

    def ack_publisher(self) -> Publisher | None:
        return self.cmd_pub

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        where = f"{scenario.source}: " if scenario.source else ""
        try:
            self.p = FourWheelSteerParams.model_validate(scenario.controller.params)
        except ValidationError as e:
            raise ConfigError(format_error(scenario.source or "scenario", e, prefix="controller.params")) from None
        self.geom, self.steer, self.drive = wheel_geometry(scenario.world.model, self.p.wheels, where)
        table = control.joint_table(scenario.world.model)
        self.names = list(table.names)
        idx = {n: i for i, n in enumerate(self.names)}
        self.i_steer = [idx[n] for n in self.steer]
        self.i_drive = [idx[n] for n in self.drive]
        self.effort = [scenario.joint(n).interface == "effort" for n in self.names]
        self.velocity_iface = [scenario.joint(n).interface == "velocity" for n in self.names]
        self.velocity_gain = scenario.controller.velocity_gain
        gains = self._gains(scenario.controller.gains, where)
        self.pids = [control.Pid(g, float(table.effort_lower[i]), float(table.effort_upper[i]))
                     for i, g in enumerate(gains)]
        limits = urdf_limits(scenario.world.urdf) if scenario.world.urdf else {}
        self.max_wheel_speed = min((limits.get(n, (0, math.inf))[1] for n in self.drive), default=math.inf)
        self.dt = 1.0 / scenario.controller.rate_hz
        self.cmd: tuple[float, float, float] | None = None
        self.cmd_ns = -1
        self.twist = (0.0, 0.0, 0.0)
        self.pose = (0.0, 0.0, 0.0)  # wheel odometry: x, y, yaw in the odom frame
        self.odom_twist = (0.0, 0.0, 0.0)
        self.drive_ref_pos: np.ndarray | None = None
        self.gyro: tuple[int, float] | None = None  # latest imu: stamp, yaw rate
        # lockstep: physics steps whose imu the odometry waits for. imu and joint_states are two keys,
        # and nothing orders them on the way here: a control step whose imu has not come yet is held
        # until it comes, so the odometry (which a navigator closes its loop on) never depends on
        # which of them arrived first
        self.imu_every = 0
        if self.p.imu_yaw_rate and scenario.clock.mode == "lockstep":
            rates = [c.rate_hz for c in scenario.sensors.values() if c.type == "imu" and c.enabled]
            if rates:
                self.imu_every = round(1.0 / (rates[0] * scenario.clock.dt))
        # lockstep with the navigator: it publishes one cmd_vel per decision step (every
        # cmd_every physics steps, from step 0), after this controller's step of the same time; a
        # later control step is held until every such cmd_vel has come, so a command never lands a
        # step early or late depending on the network (the same reason as the imu's)
        self.cmd_every = 0
        if scenario.clock.mode == "lockstep" and "navigator" in scenario.services:
            from hilsim.core.registry import service_class

            self.cmd_every = int(service_class("navigator", scenario).lockstep_period(scenario) or 0)
        self.cmds = 0  # cmd_vel samples received
        self.held: tuple[msgs.JointState, str] | None = None
        self.steps = 0

    def _gains(self, gains: dict[str, PidGains], where: str) -> list[PidGains]:
        groups = {"steering": set(self.steer), "traction": set(self.drive)}
        for k in gains:
            if k not in ("default", *groups) and k not in self.names:
                raise ConfigError(f"{where}controller.gains.{k}: not a joint of the model nor 'steering', "
                                  f"'traction' or 'default' (joints: {', '.join(self.names)})")
        out = []
        for n in self.names:
            group = next((g for g, members in groups.items() if n in members), None)
            g = gains.get(n) or (gains.get(group) if group else None) or gains.get("default")
            if g is None:
                raise ConfigError(f"{where}controller.gains: no gains for {n} (give 'steering', 'traction' "
                                  "or 'default')")
            out.append(g.model_copy())
        return out

    # ------------------------------------------------------------------ wiring
    def setup(self) -> None:
        self.cmd_pub = self.publisher(self.keys.topic("joint_commands"))
        self.odom_pub = self.publisher(self.keys.topic("odom"))
        self.subscribe(self.keys.topic("joint_states"), msgs.JointState, self.on_joint_states)
        self.subscribe(self.keys.topic("cmd_vel"), msgs.Twist, self.on_cmd_vel)
        if self.p.imu_yaw_rate:
            self.subscribe(self.keys.topic("imu"), msgs.Imu, self.on_imu)
        self.queryable(
            self.keys.topic("controller/set_parameters"), msgs.SetParameters, self.on_set_parameters,
            reject=lambda reason: msgs.SetParametersResult(successful=False, reason=reason),
        )

    def on_cmd_vel(self, msg: msgs.Twist, key: str) -> None:
        # a Twist has no stamp: it counts from the sim time it arrived at (the last control step)
        self.cmd = (msg.linear.x, msg.linear.y, msg.angular.z)
        self.cmd_ns = self.sim_ns
        self.cmds += 1
        self._release()

    def on_imu(self, msg: msgs.Imu, key: str) -> None:
        self.gyro = (msgs.ns_of(msg.header.stamp), msg.angular_velocity.z)
        self._release()

    def _waiting(self, stamp: int) -> bool:
        """Lockstep: is an input of the control step at ``stamp`` still on its way (see __init__)?"""
        dt = self.sc.dt_ns
        if self.imu_every and (stamp // dt) % self.imu_every == 0 and (self.gyro is None or self.gyro[0] < stamp):
            return True
        if self.cmd_every:
            since = stamp - self.sc.control_decimation * dt  # navigator steps up to the previous control step
            if since >= 0 and self.cmds < since // (self.cmd_every * dt) + 1:
                return True
        return False

    def _release(self) -> None:
        if self.held is not None and not self._waiting(msgs.ns_of(self.held[0].header.stamp)):
            js, k = self.held
            self.held = None
            self.on_joint_states(js, k)

    def target(self, now_ns: int) -> tuple[float, float, float]:
        """The twist asked for now: a fresh cmd_vel, else the script, else standing still; limited."""
        if self.cmd is not None and now_ns - self.cmd_ns <= round(self.p.cmd_timeout * 1e9):
            vx, vy, wz = self.cmd
        else:
            vx = vy = wz = 0.0
            t = now_ns * 1e-9
            for ts, *tw in self.p.script:
                if ts <= t + 1e-12:
                    vx, vy, wz = tw
        v = math.hypot(vx, vy)
        if v > self.p.max_speed:
            vx, vy = vx * self.p.max_speed / v, vy * self.p.max_speed / v
        wz = max(-self.p.max_yaw_rate, min(self.p.max_yaw_rate, wz))
        return vx, vy, wz

    # ------------------------------------------------------------------ control step
    def on_joint_states(self, msg: msgs.JointState, key: str) -> None:
        stamp = msgs.ns_of(msg.header.stamp)
        if self._waiting(stamp):
            self.held = (msg, key)  # this step's imu or a navigator's cmd_vel is on its way (see __init__)
            return
        if not msg.position or not msg.velocity:
            self.reject(key, "JointState without positions or velocities")
            return
        index = {n: i for i, n in enumerate(msg.name)}
        missing = [n for n in self.names if n not in index]
        if missing:
            self.reject(key, f"JointState lacks joints {missing}")
            return
        pos = np.array([msg.position[index[n]] for n in self.names])
        vel = np.array([msg.velocity[index[n]] for n in self.names])
        self.sim_ns = stamp
        angles, speeds = pos[self.i_steer], vel[self.i_drive]
        # odometry from the encoders of this step
        if self.steps:
            self.pose = steering.integrate(self.pose, self.odom_twist, self.dt)
        # the sensors publish the imu of a step before its joint_states: the gyro of this step, if any
        fresh = self.gyro is not None and stamp - self.gyro[0] < round(self.dt * 1e9)
        self.odom_twist = steering.forward(angles, speeds, self.geom, self.gyro[1] if fresh and self.gyro else None)
        # kinematics: wheel references for the twist asked for
        self.twist = self.target(stamp)
        a_ref, w_ref = steering.inverse(*self.twist, self.geom, angles.tolist(), self.max_wheel_speed)
        w_ref = np.array([w * steering.traction_scale(a - a0) for w, a, a0 in zip(w_ref, a_ref, angles, strict=True)])
        if self.drive_ref_pos is None:
            self.drive_ref_pos = pos[self.i_drive].copy()
        self.drive_ref_pos += w_ref * self.dt
        ref_pos, ref_vel, u = pos.copy(), np.zeros(len(self.names)), np.zeros(len(self.names))
        for k, (i, j) in enumerate(zip(self.i_steer, self.i_drive, strict=True)):
            ref_pos[i], ref_pos[j], ref_vel[j] = a_ref[k], self.drive_ref_pos[k], w_ref[k]
            if self.effort[i]:
                u[i] = self.pids[i].update(a_ref[k], 0.0, pos[i], vel[i], self.dt)
            elif self.velocity_iface[i]:  # a velocity-driven steering motor: close the angle here
                ref_vel[i] = self.velocity_gain * (a_ref[k] - pos[i])
            if self.effort[j]:  # speed loop: the PID's "position" is the wheel speed
                u[j] = self.pids[j].update(w_ref[k], 0.0, vel[j], 0.0, self.dt)
        header = msgs.header(stamp)
        self.cmd_pub.put(msgs.JointState(header=header, name=self.names, position=ref_pos.tolist(),
                                         velocity=ref_vel.tolist(), effort=u.tolist()))
        self.odom_pub.put(self._odometry(stamp))
        self.steps += 1

    def _odometry(self, stamp: int) -> msgs.Odometry:
        x, y, th = self.pose
        vx, vy, wz = self.odom_twist
        return msgs.Odometry(
            header=msgs.header(stamp, "odom"), child_frame_id="base_link",
            pose=msgs.PoseWithCovariance(pose=msgs.Pose(
                position=msgs.Point(x=x, y=y), orientation=msgs.Quaternion(z=math.sin(th / 2), w=math.cos(th / 2)))),
            twist=msgs.TwistWithCovariance(twist=msgs.Twist(
                linear=msgs.Vector3(x=vx, y=vy), angular=msgs.Vector3(z=wz))))

    # ------------------------------------------------------------------ live gains
    def on_set_parameters(self, req: msgs.SetParameters) -> msgs.SetParametersResult:
        why = control.set_parameters(self.pids, self.names, req.parameters)
        if why is not None:
            return msgs.SetParametersResult(successful=False, reason=why)
        return msgs.SetParametersResult(successful=True, reason=f"{len(req.parameters)} parameter(s) set")

    def health_values(self) -> dict[str, Any]:
        vx, vy, wz = self.twist
        x, y, th = self.pose
        return {
            "mode": steering.mode(vx, vy, wz),
            "twist": f"{vx:.3f},{vy:.3f},{wz:.3f}",
            "odom_pose": f"{x:.3f},{y:.3f},{th:.3f}",
            "control_steps": self.steps,
        }
