"""What the arm does: the ``planner:`` section (which planner, its budget, the criterion auto chooses for)
and the ``task:`` section (the targets to reach)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from hilsim.core.config.base import _Model

# the planner's criterion (hilsim.planning.scoring computes it): the names, and what auto chooses for by default
Criterion = Literal["length", "smoothness", "weighted"]
DEFAULT_CRITERION: Criterion = "weighted"


class PlannerConfig(_Model):
    planner: str = Field("improved_rrtstar", description="default planner, by name in the planner library (the "
                         "paper's improved RRT*; RRT-Connect's path when it finds none: ±2π and continuous joints)")
    planning_time: float = Field(1.0, gt=0, description="wall seconds per plan (realtime)")
    clearance: float = Field(0.005, ge=0, description="minimum distance to obstacles [m]")
    rate_hz: float = Field(100.0, gt=0, description="how often the planner decides (starts goals, monitors)")
    library: Path | None = Field(None, description="planner library YAML (default config/planners.yaml)")
    iterations: int | None = Field(
        None, gt=0, description="iteration budget per plan: lockstep default the library's; in realtime "
        "only when set, and planning_time still caps it"
    )
    criterion: Criterion = Field(
        DEFAULT_CRITERION, description="what planner: auto chooses for: hilsim plan evaluate's criterion "
        "(joint path length, acceleration variance, or both), plus planning time"
    )


class TaskConfig(_Model):
    targets: list[list[float]] = Field(default_factory=list)
    tolerance: float = Field(0.01, gt=0)
    settle_time: float = Field(0.3, ge=0)
    target_timeout: float = Field(30.0, gt=0, description="sim seconds per target")
