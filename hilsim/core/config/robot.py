"""The robot's sections: its world model, its joints (interface, server, a simulated drive), physics, its
sensors and its controller (control law, rate, PID gains)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from hilsim.core.config.base import SIM, _Model


class WorldConfig(_Model):
    model: Path = Field(description="MJCF world file (robot included)")
    urdf: Path | None = None
    home: list[float] | None = Field(None, description="the pose physics starts in, one value per actuated joint "
                                     "(default: the model's keyframe 'home' if it has one, else its zero pose)")


Interface = Literal["effort", "position", "velocity"]


class DriveConfig(_Model):
    """A servo drive simulated in lockstep (:mod:`hilsim.sim.drive`): its closed-loop response from
    setpoint to encoder, as ``hilsim identify`` fits it from a real drive (docs/hil.md)."""

    order: Literal[1, 2] = Field(2, description="1: position lag time_constant; 2: natural_frequency, damping_ratio")
    dead_time: float = Field(0.0, ge=0, le=1.0, description="[s] from the setpoint's stamp to the drive acting on it")
    natural_frequency: float = Field(40.0, gt=0, description="order 2: ω_n of the closed loop [rad/s]")
    damping_ratio: float = Field(1.0, gt=0, description="order 2: ζ")
    time_constant: float = Field(0.02, gt=0, description="order 1: τ [s]")
    max_velocity: float = Field(math.inf, gt=0, description="[rad/s] (inf: none)")
    max_acceleration: float = Field(math.inf, gt=0, description="[rad/s²] (inf: none)")
    resolution: float = Field(0.0, ge=0, description="the encoder's quantum [rad] (0: exact)")
    period: float = Field(0.0, ge=0, le=1.0, description="[s] between the encoder's reports (0: every physics step)")


class JointConfig(_Model):
    """How one joint is commanded and who serves it (like a ros2_control hardware interface)."""

    interface: Interface = Field("effort", description="command interface: effort, position or velocity")
    server: str = Field(SIM, description="'sim' (physics) or the name of an external server (e.g. motor-model)")
    servo_kp: float | None = Field(None, gt=0, description="simulated drive: position [N·m/rad] or velocity "
                                   "[N·m·s/rad] servo gain (default 100 / 10)")
    servo_kv: float | None = Field(None, ge=0, description="simulated position drive: damping [N·m·s/rad] (default 5)")
    drive: DriveConfig | None = Field(None, description="a position or velocity joint simulated by physics as this "
                                      "drive (hilsim.sim.drive: dead time, closed loop, limits, encoder) instead of "
                                      "MuJoCo's servo; what hilsim identify writes for a twin")


class PhysicsConfig(_Model):
    truth_imu_site: str | None = "imu"
    gravity_compensation: list[str] = Field(
        default_factory=list, description="bodies whose gravity is compensated (names or glob patterns, e.g. 'link_*')"
    )
    follow_extrapolation: float = Field(
        0.0, ge=0, le=0.1, description="external joints: carry a server's last report forward at its velocity for "
        "at most this many seconds (e.g. one report period of a drive that reports every 10 ms); 0 = hold it",
    )
    server_timeout: float = Field(
        0.25, gt=0, description="wall seconds without state from an external joint server before it is a fault"
    )
    tf_rate_hz: float = Field(50.0, ge=0, description="/tf of the URDF's moving joints (0: off)")


class SensorConfig(BaseModel):
    """One emulated sensor; ``type`` picks the class, the other fields are its parameters."""

    model_config = ConfigDict(extra="allow")
    type: str
    rate_hz: float = Field(100.0, gt=0)
    enabled: bool = True


class PidGains(_Model):
    kp: float = Field(ge=0)
    ki: float = Field(0.0, ge=0)
    kd: float = Field(0.0, ge=0)
    i_limit: float = Field(math.inf, gt=0, description="anti-windup: limit on |ki * integral|")
    output_limit: float | None = Field(None, gt=0)
    feedforward: float = Field(0.0, ge=0, description="velocity feed-forward gain")


class ControllerConfig(_Model):
    type: str = Field("joint_trajectory", description="control law, by name (built-in or hilsim.controllers plug-in)")
    rate_hz: float = Field(1000.0, gt=0)
    velocity_gain: float = Field(
        10.0, ge=0, description="velocity-interface joints: command = v_ref + velocity_gain·(p_ref − p) [1/s]"
    )
    gains: dict[str, PidGains] = Field(default_factory=dict, description="per joint name, or 'default'")
    hold_timeout: float = Field(0.05, gt=0, description="sim seconds without joint_states before holding")
    params: dict[str, Any] = Field(
        default_factory=dict, description="settings of the control law named by `type`, validated by its class "
        "(e.g. four_wheel_steer: max_speed, cmd_timeout, script)",
    )
