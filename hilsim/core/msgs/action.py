"""The planner's move action (``hilsim_msgs/action/Move_…``) and its MoveIt-like error codes."""

from dataclasses import dataclass, field

from pycdr2 import IdlStruct
from pycdr2.types import float64, int32, sequence

from hilsim.core.msgs.builtin import Header
from hilsim.core.msgs.geometry import Pose
from hilsim.core.msgs.trajectory import JointTrajectory


@dataclass
class MoveGoal(IdlStruct, typename="hilsim_msgs/action/Move_Goal"):
    """Goal of the planner's move action. ``target_kind`` is ``joints`` (``joint_positions``)
    or ``pose`` (``pose`` of the tool in the world frame; ``use_orientation`` says whether
    its orientation counts). Zero ``planning_time`` means the service default."""

    goal_id: str = ""
    target_kind: str = "joints"
    joint_names: sequence[str] = field(default_factory=list)
    joint_positions: sequence[float64] = field(default_factory=list)
    pose: Pose = field(default_factory=Pose)
    use_orientation: bool = False
    planner: str = ""
    planning_time: float64 = 0.0
    execute: bool = True


@dataclass
class GoalResponse(IdlStruct, typename="hilsim_msgs/action/Move_GoalResponse"):
    goal_id: str = ""
    accepted: bool = False
    reason: str = ""


@dataclass
class CancelRequest(IdlStruct, typename="hilsim_msgs/action/Move_Cancel"):
    goal_id: str = ""


@dataclass
class MoveFeedback(IdlStruct, typename="hilsim_msgs/action/Move_Feedback"):
    header: Header = field(default_factory=Header)
    goal_id: str = ""
    state: str = ""  # planning | executing | settling
    progress: float64 = 0.0


@dataclass
class MoveResult(IdlStruct, typename="hilsim_msgs/action/Move_Result"):
    header: Header = field(default_factory=Header)
    goal_id: str = ""
    success: bool = False
    error_code: int32 = 0
    message: str = ""
    trajectory: JointTrajectory = field(default_factory=JointTrajectory)
    planning_time: float64 = 0.0
    execution_error: sequence[float64] = field(default_factory=list)
    planner: str = ""


# error codes of MoveResult (MoveIt-like)
SUCCESS = 1
FAILURE = 99999
PLANNING_FAILED = -1
INVALID_GOAL = -2
TIMED_OUT = -6
CANCELED = -7
CONTROL_FAILED = -4
GOAL_IN_COLLISION = -10
GOAL_OUT_OF_LIMITS = -11
NO_IK_SOLUTION = -31
