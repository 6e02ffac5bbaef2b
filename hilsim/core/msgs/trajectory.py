"""trajectory_msgs."""

from dataclasses import dataclass, field

from pycdr2 import IdlStruct
from pycdr2.types import float64, sequence

from hilsim.core.msgs.builtin import Duration, Header


@dataclass
class JointTrajectoryPoint(IdlStruct, typename="trajectory_msgs/msg/JointTrajectoryPoint"):
    positions: sequence[float64] = field(default_factory=list)
    velocities: sequence[float64] = field(default_factory=list)
    accelerations: sequence[float64] = field(default_factory=list)
    effort: sequence[float64] = field(default_factory=list)
    time_from_start: Duration = field(default_factory=Duration)


@dataclass
class JointTrajectory(IdlStruct, typename="trajectory_msgs/msg/JointTrajectory"):
    """header.stamp is the sim time at which the first point applies; an empty
    trajectory (no points) means: stop and hold the current position (ROS convention)."""

    header: Header = field(default_factory=Header)
    joint_names: sequence[str] = field(default_factory=list)
    points: sequence[JointTrajectoryPoint] = field(default_factory=list)
