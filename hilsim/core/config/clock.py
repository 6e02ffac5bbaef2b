"""The ``clock:`` section: lockstep or realtime, the physics step, and the waits around it."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from hilsim.core.config.base import _Model


class ClockConfig(_Model):
    mode: Literal["lockstep", "realtime"] = "lockstep"
    dt: float = Field(0.001, gt=0, le=0.1, description="physics step [s]")
    ack_timeout: float = Field(
        30.0, gt=0, description="wall seconds physics waits for a lockstep ack before the run is stalled "
        "(longer than the planner's wall-clock cap on one plan, which a lockstep step may include)",
    )
    max_age: float = Field(
        0.05, ge=0, description="realtime: a received sample older than this (wall seconds since it was sent) is "
        "dropped as stale and counted, so a service that fell behind catches up (streams only: a trajectory, "
        "given once, is never dropped); 0 = keep every sample",
    )
    controller_lag: int = Field(
        0, ge=0, le=1, description="lockstep: steps between the measurement a controller's command answers and the "
        "step it acts on; 1 models the one-sample computation delay of a digital controller and lets physics, "
        "sensors and controller work on neighbouring steps at once (docs/keys.md, docs/performance.md)",
    )
    start_delay: float = Field(
        0.5, ge=0, description="wall seconds between every service being live and step 0 (peers finish connecting)"
    )
    start_timeout: float = Field(
        120.0, gt=0, description="wall seconds hilsim up and physics wait for every service to announce itself "
        "before the run fails (hilsim up --wait sets it)",
    )
