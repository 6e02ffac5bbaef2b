"""The ``navigator:`` section of a rover's scenario (services/navigator.py reads it; hilsim plan evaluate on a
rover too): the map, the footprint, the planner and the path follower."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator


class FootprintConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    length: float = Field(1.0, gt=0, description="m, along x (wheels included)")
    width: float = Field(0.9, gt=0, description="m, along y (wheels included)")
    circles: int = Field(2, ge=1, le=8, description="circles along x that cover the rectangle")


class FollowerConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    max_speed: float = Field(0.6, gt=0, description="m/s")
    min_speed: float = Field(0.06, gt=0, description="m/s while moving")
    max_yaw_rate: float = Field(1.0, gt=0, description="rad/s")
    accel: float = Field(0.4, gt=0, description="m/s², braking profile to cusps and the goal")
    lookahead: float = Field(0.4, gt=0, description="m")
    k_yaw: float = Field(2.0, gt=0, description="1/s")
    k_final: float = Field(1.0, gt=0, description="1/s: speed per metre to the goal")
    xy_tolerance: float = Field(0.06, gt=0, description="m: translation stops this close to the goal")
    yaw_tolerance: float = Field(0.05, gt=0, description="rad: final yaw")
    cusp_tolerance: float = Field(0.1, gt=0, description="m")


class NavigatorConfig(BaseModel):
    """The ``navigator:`` section of a scenario."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    rate_hz: float = Field(20.0, gt=0, description="decision ticks (must divide controller.rate_hz)")
    resolution: float = Field(0.05, gt=0, le=1.0, description="grid cell [m]")
    z_band: tuple[float, float] = Field((0.1, 0.7), description="heights [m] whose geometry is an obstacle")
    bounds: tuple[float, float, float, float] | None = Field(
        None, description="x_min, x_max, y_min, y_max of the map (default: the static geometry + 1 m)")
    footprint: FootprintConfig = Field(default_factory=FootprintConfig)
    clearance: float = Field(0.05, ge=0, description="m added to the footprint's circles")
    turning_radius: float = Field(0.8, gt=0, description="Reeds–Shepp turning radius [m]")
    planner: str = Field("RRTConnect", description="OMPL geometric planner")
    planner_range: float = Field(3.0, gt=0, description="m: the planner's longest tree edge (setRange)")
    attempts: int = Field(3, ge=1, le=20, description="plans per goal; the shortest is followed")
    iterations: int = Field(20000, gt=0, description="iteration budget per plan (deterministic)")
    planning_time: float = Field(5.0, gt=0, description="wall-clock cap per plan [s]")
    goal_tolerance: float = Field(0.1, gt=0, description="m: a goal counts as reached within this (odometry)")
    goal_timeout: float = Field(30.0, gt=0, description="sim s per goal beyond the path's time at max_speed")
    replan_distance: float = Field(0.5, gt=0, description="m off the path before it is planned again")
    max_replans: int = Field(2, ge=0, description="replans per goal (off the path, or stopped short of the goal)")
    map_period: float = Field(5.0, gt=0, description="sim s between map publications")
    follower: FollowerConfig = Field(default_factory=FollowerConfig)

    @model_validator(mode="after")
    def _band(self) -> NavigatorConfig:
        if not self.z_band[1] > self.z_band[0]:
            raise ValueError(f"z_band must be [low, high] with high > low (got {list(self.z_band)})")
        if self.bounds is not None and not (self.bounds[1] > self.bounds[0] and self.bounds[3] > self.bounds[2]):
            raise ValueError(f"bounds must be [x_min, x_max, y_min, y_max] with max > min (got {list(self.bounds)})")
        return self
