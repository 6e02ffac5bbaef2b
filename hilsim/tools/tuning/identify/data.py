"""What a drive did in a recorded run: its joint's commands and its encoder's reports, from the run's bag.

A run directory written by ``hilsim up`` or by ``hilsim identify`` holds ``scenario.yaml`` (the run's
resolved scenario: its keys, which joint is served by what) and ``bag/`` (rosbag2, MCAP). For one joint
this reads, in sim time (the stamps; the recorder's receive times wander by hundreds of ms on a busy
machine):

- the setpoints the controller sent it: ``joint_commands`` (position and its velocity feed-forward;
  a velocity joint: the velocity), stamped with the measurement they answer;
- the setpoints as the bridge passed them on: ``hw/<server>/setpoints`` (``bridge-can.setpoints``, which
  ``hilsim identify`` turns on), each stamped with the sim time it went on the bus: the fit takes
  them as the drive's input, so that a command held up on its way (a busy machine) is not taken for
  the drive's own slowness, and the way from the controller's step to the bus is measured apart;
- the drive's reports: ``hw/<server>/joint_states``, each stamped with the sim time it came from the
  drive (:mod:`hilsim.core.simclock`): what the fit compares with, and the encoder's quantum and rate;
- what physics had of the joint: ``truth/joint_states`` (the drive's latest report as it reached
  physics), compared with instead when the record has no reports of the joint: the steps where it
  changed are when a report arrived.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hilsim.core import msgs
from hilsim.core.config import SIM, ConfigError, Scenario
from hilsim.core.keys import Keys
from hilsim.core.scenario import load_scenario
from hilsim.record.bag_read import BagError, open_bag


@dataclass
class JointRecord:
    """One joint of a run: arrays in sim seconds and rad (rad/s)."""

    joint: str
    interface: str  # position or velocity
    server: str  # who served it in the run (a drive's bridge, motor-model, or sim)
    cmd_t: np.ndarray  # setpoints: stamp
    cmd_p: np.ndarray  # position setpoint (velocity joints: nan)
    cmd_v: np.ndarray  # velocity (feed-forward, or the velocity setpoint)
    out_t: np.ndarray  # the joint's state in the simulation, every step
    out_p: np.ndarray
    out_v: np.ndarray
    hw_t: np.ndarray  # the server's reports (stamped with the sim time they came from the drive)
    hw_p: np.ndarray
    hw_v: np.ndarray
    sp_t: np.ndarray  # the setpoints as they went on the bus (empty if the server did not publish them)
    sp_p: np.ndarray
    sp_v: np.ndarray

    def window(self, t0: float, t1: float) -> JointRecord:
        """The part from ``t0`` to ``t1`` [s] (setpoints from before ``t0`` kept: the one in force matters)."""
        c = self.cmd_t <= t1
        o = (self.out_t >= t0) & (self.out_t <= t1)
        h = (self.hw_t >= t0) & (self.hw_t <= t1)
        s = self.sp_t <= t1
        return JointRecord(self.joint, self.interface, self.server, self.cmd_t[c], self.cmd_p[c], self.cmd_v[c],
                           self.out_t[o], self.out_p[o], self.out_v[o], self.hw_t[h], self.hw_p[h], self.hw_v[h],
                           self.sp_t[s], self.sp_p[s], self.sp_v[s])

    def inputs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """(t, position, velocity) of what the drive was given, and the way to it: with the setpoints as the
        server sent them (20 or more), those, and for each the time since the stamp of the command it came
        from [s]; else the commands at their stamps, and None."""
        if self.sp_t.size < 20:
            return self.cmd_t, self.cmd_p, self.cmd_v, None
        way = []
        k, n = 0, self.cmd_t.size
        for t, p, v in zip(self.sp_t.tolist(), self.sp_p.tolist(), self.sp_v.tolist(), strict=True):
            # the commands in order: the first not yet matched with the same setpoint (a command the server
            # held back, e.g. while faulted, has no setpoint and is passed over)
            j = k
            while j < n and self.cmd_t[j] <= t and not (self._same(self.cmd_p[j], p) and self.cmd_v[j] == v):
                j += 1
            if j < n and self.cmd_t[j] <= t:
                way.append(t - self.cmd_t[j])
                k = j + 1
        return self.sp_t, self.sp_p, self.sp_v, np.array(way)

    @staticmethod
    def _same(a: float, b: float) -> bool:
        return a == b or (np.isnan(a) and b == 0.0)

    def measured(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t, position, velocity) of the drive as measured: its reports, at the sim time each came from the
        drive; without reports (fewer than 20), the truth at the steps where it changed (when a report
        reached physics: the steps between hold it)."""
        if self.hw_t.size >= 20 and float(np.ptp(self.hw_t)) > 0.0:
            return self.hw_t, self.hw_p, self.hw_v
        changed = (np.diff(self.out_p) != 0.0) | (np.diff(self.out_v) != 0.0)
        i = np.concatenate([[0], np.nonzero(changed)[0] + 1])
        return self.out_t[i], self.out_p[i], self.out_v[i]


def run_scenario(run_dir: Path) -> Scenario:
    """The resolved scenario a run was made with (``<run>/scenario.yaml``)."""
    path = run_dir / "scenario.yaml"
    if not path.is_file():
        raise ConfigError(f"{run_dir}: not a run directory (no scenario.yaml; expected what hilsim up writes)")
    return load_scenario(path)


def read_joints(run_dir: Path, joints: list[str]) -> dict[str, JointRecord]:
    """Every named joint's record in the run at ``run_dir`` (one pass over its bag)."""
    sc = run_scenario(run_dir)
    keys = Keys.of(sc)
    k_cmd, k_truth = keys.topic("joint_commands"), keys.truth("joint_states")
    servers = {j: sc.joint(j).server for j in joints}
    k_hw = {keys.server_state(s): s for s in set(servers.values()) if s != SIM}
    for j in joints:
        if sc.joint(j).interface not in ("position", "velocity"):
            raise ConfigError(f"{run_dir}: joints.{j}.interface: {sc.joint(j).interface!r}; a drive is identified "
                              f"from its position or velocity setpoints (interface position or velocity)")
    cmd: dict[str, list[tuple[float, float, float]]] = {j: [] for j in joints}
    out: dict[str, list[tuple[float, float, float]]] = {j: [] for j in joints}
    hw: dict[str, list[tuple[float, float, float]]] = {j: [] for j in joints}
    sp: dict[str, list[tuple[float, float, float]]] = {j: [] for j in joints}
    k_sp = {keys.server_setpoints(s) for s in set(servers.values()) if s != SIM}
    try:
        bag = open_bag(run_dir)
        for m in bag.messages():
            if m.key == k_cmd:
                _take(cmd, msgs.decode(msgs.JointState, m.data), commands=True)
            elif m.key == k_truth:
                _take(out, msgs.decode(msgs.JointState, m.data))
            elif m.key in k_hw:
                _take(hw, msgs.decode(msgs.JointState, m.data))
            elif m.key in k_sp:
                _take(sp, msgs.decode(msgs.JointState, m.data), commands=True)
    except (BagError, OSError) as e:
        raise ConfigError(f"{run_dir}: its bag cannot be read: {e}") from None
    recs = {}
    for j in joints:
        if len(cmd[j]) < 10 or len(out[j]) < 10:
            raise ConfigError(f"{run_dir}: the bag has {len(cmd[j])} commands and {len(out[j])} states of {j}: too few "
                              f"to identify it (was the recorder on, recording joint_commands and truth/joint_states?)")
        c = np.array(sorted(cmd[j]))
        o = np.array(sorted(out[j]))
        h = np.array(sorted(hw[j])) if hw[j] else np.zeros((0, 3))
        h = h[h[:, 0] > 0.0]  # a report stamped 0: before the server knew the sim time
        s = np.array(sorted(sp[j])) if sp[j] else np.zeros((0, 3))
        s = s[s[:, 0] > 0.0]
        recs[j] = JointRecord(j, sc.joint(j).interface, servers[j], c[:, 0], c[:, 1], c[:, 2], o[:, 0], o[:, 1],
                              o[:, 2], h[:, 0], h[:, 1], h[:, 2], s[:, 0], s[:, 1], s[:, 2])
    return recs


def _take(into: dict[str, list[tuple[float, float, float]]], js: msgs.JointState, commands: bool = False) -> None:
    t = msgs.ns_of(js.header.stamp) * 1e-9
    n = len(js.name)
    has_p, has_v = len(js.position) == n, len(js.velocity) == n
    for k, name in enumerate(js.name):
        if name in into:
            p = js.position[k] if has_p else np.nan
            v = js.velocity[k] if has_v else (0.0 if commands else np.nan)
            into[name].append((t, p, v))
