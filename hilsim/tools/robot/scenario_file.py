"""The scenario and planner library an import writes (``DIR/NAME.yaml``, ``DIR/planners.yaml``): the built-in
arm's scenario (``config/arm.yaml``) made for the imported robot, with comments saying where each value came
from, so a lab edits it as its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import yaml

from hilsim.core.config import CONFIG_DIR
from hilsim.tools.robot.urdf import Joint

BANDWIDTH_HZ = 2.0  # the model-based starting gains: a critically damped loop of this natural frequency
DEFAULT_PLANNER = "improved_rrtstar"  # the paper's, as the built-in arm (RRT-Connect's path when it has none)


@dataclass
class Gains:
    kp: float
    ki: float
    kd: float
    i_limit: float

    def yaml(self) -> str:
        return f"{{kp: {self.kp:.4g}, ki: {self.ki:.4g}, kd: {self.kd:.4g}, i_limit: {self.i_limit:.4g}}}"


def joint_inertia(model: mujoco.MjModel, qpos: np.ndarray, joint: Joint) -> float:
    """The arm's inertia seen by one joint at ``qpos`` (its diagonal entry of the mass matrix) [kg·m² or kg]."""
    d = mujoco.MjData(model)
    d.qpos[:] = qpos
    mujoco.mj_forward(model, d)
    full = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, d, full)  # MuJoCo 4: (m, d, dst)
    dof = model.jnt_dofadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint.name)]
    return max(float(full[dof, dof]), 1e-4)


def model_gains(model: mujoco.MjModel, home_qpos: np.ndarray, joints: list[Joint]) -> dict[str, Gains]:
    """A PD per joint from the arm's inertia at home: kp = M ω², kd = 2 M ω (critically damped at
    :data:`BANDWIDTH_HZ`); where the tuner is not run these are the gains, else its starting point."""
    w = 2 * math.pi * BANDWIDTH_HZ
    out = {}
    for j in joints:
        m_ii = joint_inertia(model, home_qpos, j)
        effort = j.effort if math.isfinite(j.effort) else 100.0
        out[j.name] = Gains(m_ii * w * w, 0.0, 2 * m_ii * w, 0.1 * effort)
    return out


def write_library(path: Path, joints: list[Joint]) -> None:
    """The built-in planner library (``config/planners.yaml``), its trajectory limits one per joint of this
    robot: the velocity from the URDF (at most 1.5 rad/s, or 0.5 m/s for a prismatic joint), the
    acceleration twice, the jerk ten times that. Every other setting as shipped (``auto``'s model path made
    absolute: the library moved)."""
    data = yaml.safe_load((CONFIG_DIR / "planners.yaml").read_text())
    for spec in data.get("planners", {}).values():
        model = (spec.get("params") or {}).get("model")
        if model is not None and not Path(model).is_absolute():
            spec["params"]["model"] = str((CONFIG_DIR / model).resolve())
    vel = [min(j.velocity if math.isfinite(j.velocity) else 1.0, 0.5 if j.kind == "prismatic" else 1.5) for j in joints]
    data["limits"] = {"velocity": [round(v, 4) for v in vel], "acceleration": [round(2 * v, 4) for v in vel],
                      "jerk": [round(10 * v, 4) for v in vel]}
    head = ("# The planner library of an imported robot: config/planners.yaml with trajectory limits one per joint\n"
            f"# ({', '.join(j.name for j in joints)}). Written by hilsim robot import.\n")
    path.write_text(head + yaml.safe_dump(data, sort_keys=False, width=120))


def _vec(q: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:.4f}" for v in q) + "]"


def write_scenario(path: Path, name: str, urdf_src: Path, joints: list[Joint], gains: dict[str, Gains],
                   home: np.ndarray, home_how: str, targets: list[np.ndarray], planner: str, tuned: str) -> None:
    names = ", ".join(j.name for j in joints)
    g_lines = "\n".join(f"    {n}: {g.yaml()}" for n, g in gains.items())
    t_lines = "\n".join(f"    - {_vec(t)}" for t in targets)
    path.write_text(f"""\
# {name}: imported from {urdf_src} by `hilsim robot import` (docs/robots.md).
# Run: hilsim up {path.name}   (paths are relative to this file)
# Joints, in the order of every per-joint list below: {names}
name: {name}
robot: {name}
prefix: hilsim
seed: 0
services: [physics, sensors, controller, planner, logger]

clock:
  mode: lockstep
  dt: 0.001
  controller_lag: 1

world:
  model: {name}.xml      # the arm on its pedestal; meshes in meshes/
  urdf: {name}.urdf      # the lab's URDF, its meshes pointing into meshes/ (robot_description, tf, recording)
  # where physics starts: {home_how}
  home: {_vec(home)}

physics:
  truth_imu_site: imu
  gravity_compensation: ["*"]   # as the built-in arm: link gravity off, inertia kept

joints:
  default: {{interface: effort, server: sim}}

sensors:
  encoders:
    type: encoder
    rate_hz: 1000
    resolution: 0.0001
    noise_std: 0.00002
  imu:
    type: imu
    rate_hz: 200
    accel_noise_std: 0.02
    gyro_noise_std: 0.002

controller:
  rate_hz: 1000
  gains:
    # {tuned}
    default: {{kp: 50.0, ki: 0.0, kd: 5.0, i_limit: 1.0, feedforward: 0.0}}
{g_lines}

planner:
  planner: {planner}
  planning_time: 1.0
  clearance: 0.005
  library: planners.yaml

task:
  tolerance: 0.01
  settle_time: 0.3
  target_timeout: 30.0
  # collision-free, inside the joints' ranges, each planned to and from home and the others at import
  targets:
{t_lines}

logger:
  enabled: true
  out_dir: runs
""")


def write_hil_overlay(path: Path, scenario_name: str, joint: Joint, home: float, inertia: float) -> None:
    """``hil-can.yaml``: hardware in the loop for the imported arm, its first joint on a CAN drive (the project's
    emulated ODrive by default, as ``config/hil/can-emulated.yaml`` does for the built-in arm; a real drive on
    can0: docs/hil.md). Any other joint: change the joint's name in both places.

    Realtime at the lean rates of ``config/arm-lean.yaml`` (500 Hz physics, 250 Hz control): at 1 kHz a 2-core
    machine running the seven processes misses half its ticks and the controller holds for want of joint
    states. The emulated drive takes its limits from the URDF (velocity; acceleration: effort over the
    joint's inertia at home) and starts where physics starts (home), not at zero."""
    base = (CONFIG_DIR / "hil" / "can-emulated.yaml").resolve()
    vel = f"{joint.velocity:.4g}" if math.isfinite(joint.velocity) and joint.velocity > 0 else ".inf"
    acc = f"{joint.effort / max(inertia, 1e-6):.4g}" if math.isfinite(joint.effort) and joint.effort > 0 else ".inf"
    path.write_text(f"""\
# Hardware in the loop: {joint.name} on a CAN drive (the project's emulated ODrive, its own process).
# Run: hilsim up {scenario_name} --hil {path.name}   (realtime: a drive lives on the wall clock)
# Another joint, or several: name it under joints and bridge-can.joints (a node_id each; docs/hil.md).
extends: {base}
# the lean rates of config/arm-lean.yaml: seven realtime processes on a small machine keep the wall clock
clock: {{dt: 0.002}}
controller: {{rate_hz: 250}}
sensors:
  encoders: {{rate_hz: 250}}
  imu: {{rate_hz: 50}}
planner: {{rate_hz: 50}}
joints!:
  default: {{interface: effort, server: sim}}
  {joint.name}: {{interface: position, server: bridge-can}}
bridge-can:
  joints!:
    {joint.name}: {{node_id: 0, gear_ratio: 1.0, direction: 1, offset: 0.0}}
drive-emulator:
  encoder_period: 0.004                  # one estimate per two physics steps, as 2 ms at 1 kHz
  initial_position: {{{joint.name}: {home:.6g}}}   # where physics starts (world.home)
  max_velocity: {vel}                   # the URDF's velocity limit [rad/s]
  max_acceleration: {acc}               # the URDF's effort over the joint's inertia at home [rad/s²]
""")
