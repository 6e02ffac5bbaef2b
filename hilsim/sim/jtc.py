"""A trajectory's time as ROS 2's joint_trajectory_controller treats it: which trajectory is taken, and
what the reference is at each step.

Reads and writes no key: :mod:`hilsim.services.controller` hands it every trajectory (on its topics or
as a FollowJointTrajectory goal) and samples the reference from it each control step.

The rules (JTC's ``validate_trajectory_msg`` and its trajectory replacement):

- stamp zero means now (the control step the trajectory arrives at); a stamp in the future starts then;
- a newer trajectory (by arrival) replaces the one followed or pending *from its own start*: before it
  starts, what was commanded goes on; whatever was pending from that start on is dropped. A trajectory
  is never refused because an earlier one is stamped later (that rule would hand one far-stamped
  message the power to lock every later one out);
- one whose last point lies in the past on arrival is refused (JTC: "ends in the past"), unless the
  caller knows it is the planner's own, handed again to a restarted controller (``ended_ok``: then its
  end is held);
- a stamp farther ahead of sim time than ``max_ahead_ns``, or one that reads as wall-clock time while
  sim time does not, is refused with a reason that names ``use_sim_time`` (a node not on sim time stamps
  with the wall clock: 1.7e9 s ahead, and it would wait for ever);
- joint names in any order; a subset only if ``partial`` (JTC's ``allow_partial_joints_goal``); an
  empty trajectory (no points) holds the arm where it is.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from datetime import UTC, datetime

import numpy as np

from hilsim.core import msgs
from hilsim.sim.control import TrajectorySampler

# a stamp within this of the wall clock, on a run whose sim time is not, reads as wall-clock time
WALL_WINDOW_NS = 7 * 86_400 * 1_000_000_000


@dataclass(frozen=True)
class Rules:
    """What the controller takes: ``max_ahead_ns`` (how far after sim time a trajectory may start),
    ``partial`` (a subset of the joints is taken)."""

    max_ahead_ns: int
    partial: bool = True


def _iso(ns: int) -> str:
    return datetime.fromtimestamp(ns * 1e-9, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


# what a refusal is about (the FollowJointTrajectory action turns it into its error code)
JOINTS, ENDED, AHEAD = "joints", "ended", "ahead"


def refusal(msg: msgs.JointTrajectory, now_ns: int, joints: list[str], rules: Rules, *, ended_ok: bool = False,
            wall_ns: int | None = None) -> tuple[str, str] | None:
    """Why ``msg``, arriving at sim time ``now_ns``, is not taken under the time and joint rules (module
    docstring): (``JOINTS``, ``ENDED`` or ``AHEAD``, the reason); None if it is taken. Its values (sizes,
    limits, finite) are the sampler's to judge."""
    if not msg.points:
        return None  # hold where the arm is
    names = list(msg.joint_names)
    if not names:
        return JOINTS, "the trajectory names no joints"
    if not rules.partial and sorted(set(names)) != sorted(joints):
        return JOINTS, (f"the trajectory names {len(set(names))} of the {len(joints)} joints ({', '.join(names)}); "
                f"a subset is refused (controller.params.allow_partial_joints_goal: false)")
    stamp = msgs.ns_of(msg.header.stamp)
    if not stamp:
        return None  # now
    ahead = stamp - now_ns
    if ahead > rules.max_ahead_ns:
        wall = time.time_ns() if wall_ns is None else wall_ns
        if abs(stamp - wall) < WALL_WINDOW_NS and abs(now_ns - wall) >= WALL_WINDOW_NS:
            return AHEAD, (f"stamped {stamp * 1e-9:.3f} s ({_iso(stamp)}), wall-clock time, while sim time is "
                    f"{now_ns * 1e-9:.3f} s: the sender is not on sim time (use_sim_time:=true, or stamp 0 for now)")
        return AHEAD, (f"starts {ahead * 1e-9:.3f} s after sim time {now_ns * 1e-9:.3f} s, more than "
                f"controller.params.max_start_ahead ({rules.max_ahead_ns * 1e-9:g} s): a clock that is not "
                f"sim time? (use_sim_time:=true, or stamp 0 for now)")
    end = stamp + msgs.ns_of(msg.points[-1].time_from_start)
    if end < now_ns and not ended_ok:
        return ENDED, (f"the trajectory ended at {end * 1e-9:.3f} s, before it arrived at {now_ns * 1e-9:.3f} s of "
                f"sim time (ends in the past)")
    return None


@dataclass
class Segment:
    """A trajectory taken: its sampler and who sent it (``planner``, ``joint_trajectory``, a goal)."""

    sampler: TrajectorySampler
    source: str


@dataclass
class Timeline:
    """The command over sim time: the segment being followed, those pending (each starting later than
    the one before), and the setpoint held when none is (before the first, after an empty trajectory)."""

    hold: np.ndarray
    current: Segment | None = None
    pending: list[Segment] = field(default_factory=list)

    def reference_at(self, ns: int) -> np.ndarray:
        """The commanded position at sim time ``ns`` as things stand (what a trajectory starting then
        starts from, for the joints it does not name and before its first point)."""
        before = [s for s in self.pending if s.sampler.start_ns <= ns]
        if before:
            return before[-1].sampler.sample(ns)[0]
        if self.current is not None:
            return self.current.sampler.sample(ns)[0]
        return self.hold

    def replace(self, seg: Segment) -> None:
        """``seg`` replaces what was commanded from its start on (a start at or before now: at once)."""
        start = seg.sampler.start_ns
        self.pending = [s for s in self.pending if s.sampler.start_ns < start] + [seg]

    def stop(self, at: np.ndarray) -> None:
        """Hold ``at``: nothing followed or pending."""
        self.current, self.pending, self.hold = None, [], np.array(at, float)

    def advance(self, now_ns: int) -> None:
        """Switch to the latest pending segment that has started."""
        while self.pending and self.pending[0].sampler.start_ns <= now_ns:
            self.current = self.pending.pop(0)

    def sample(self, now_ns: int, zero: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.current is not None:
            return self.current.sampler.sample(now_ns)
        return self.hold, zero

    def holds(self, sampler: TrajectorySampler) -> bool:
        """Whether ``sampler`` is still followed or pending (not yet replaced)."""
        return (self.current is not None and self.current.sampler is sampler) or any(
            s.sampler is sampler for s in self.pending)

    def last(self) -> Segment | None:
        """The segment commanded last in time (pending, else followed)."""
        return self.pending[-1] if self.pending else self.current
