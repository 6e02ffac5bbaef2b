"""The joint controller's parameters: ``controller.params`` (its schema) and live gain changes.

A part of :class:`hilsim.services.controller.ControllerService` (one of its bases, not a service of its own).
:class:`Params` is ``controller.params`` of the joint_trajectory controller, checked when the service is
built. Live gains: all-or-nothing by :func:`hilsim.sim.control.set_parameters`, effective at the next
control step, kept for a restarted controller (:mod:`hilsim.core.restart`) and counted in
``gains_version``, which the fleet driver (robots as arrays) watches.

Serves ``<prefix>/<robot>/controller/set_parameters`` (rcl_interfaces SetParameters
``<joint>.<kp|ki|kd|i_limit|output_limit|feedforward>`` → SetParametersResult; the queryable is the
service's setup). Writes nothing of its own: the gains in force are in the service's health.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from hilsim.core import msgs
from hilsim.core.restart import keep
from hilsim.core.service import Service
from hilsim.sim import control


class Params(BaseModel):
    """``controller.params`` of the joint_trajectory controller."""

    model_config = ConfigDict(extra="forbid")
    action_ns: str = Field("follow_joint_trajectory", description="name of the FollowJointTrajectory action below "
                           "the robot's namespace (absolute if it starts with '/'); empty: no action")
    action_feedback_hz: float = Field(20.0, gt=0, description="feedback rate of the action [1/s of sim time]")
    goal_time_tolerance: float = Field(1.0, gt=0, description="how long after a goal's last point the joints "
                                       "may take to be within tolerance, when the goal gives no time [s]")
    max_start_ahead: float = Field(30.0, gt=0, description="a trajectory stamped to start later than this after "
                                   "sim time is refused (a sender not on sim time: use_sim_time) [s]")
    allow_partial_joints_goal: bool = Field(True, description="take a trajectory that names only some of the "
                                            "joints (the others keep their command), as ROS 2's JTC parameter")


class ControllerParameters(Service):
    """The controller's live gains (:class:`hilsim.services.controller.ControllerService` sets these attributes)."""

    pids: list[control.Pid]
    names: list[str]
    live_gains: dict[str, float]  # live gain changes, kept for a restarted controller
    gains_version: int

    # ------------------------------------------------------------------ live gains
    def on_set_parameters(self, req: msgs.SetParameters) -> msgs.SetParametersResult:
        why = control.set_parameters(self.pids, self.names, req.parameters)
        if why is not None:
            return msgs.SetParametersResult(successful=False, reason=why)
        if req.parameters:
            self.log.info("gains changed: %s", ", ".join(f"{p.name}={p.value:g}" for p in req.parameters))
            self.live_gains.update({p.name: p.value for p in req.parameters})
            self.gains_version += 1  # the fleet driver (robots as arrays) takes them at its next step
            keep(self.sc, self.name, {"gains": self.live_gains})
        return msgs.SetParametersResult(successful=True, reason=f"{len(req.parameters)} parameter(s) set")
