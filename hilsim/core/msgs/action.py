"""The planner's move action (``hilsim_msgs/action/Move_…``) and its MoveIt-like error codes.

MoveGoal, MoveResult and MoveFeedback are the goal, result and feedback of the ROS 2 action
``hilsim_msgs/action/Move`` (the planner serves it as ``/<robot>/move``); the parts rosidl derives
from them (``Move_SendGoal_Request`` …) follow. MoveGoal also travels alone, with GoalResponse and
CancelRequest, in hilsim's own goal protocol (``planner/goal``, ``planner/cancel``).
"""

from dataclasses import dataclass, field

from pycdr2 import IdlStruct
from pycdr2.types import float64, int8, int32, sequence

from hilsim.core.msgs.builtin import Header, Time
from hilsim.core.msgs.control import STATUS_UNKNOWN, UUID, ServiceEventInfo
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
    planner: str = ""  # the planner planning (for planner: auto, the one it picked), once known
    choice: str = ""  # planner: auto: what it picked and why (predicted scores), else empty


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
    planner: str = ""  # the planner that planned (for planner: auto, the one it picked or fell back to)
    choice: str = ""  # planner: auto: what it picked and why (predicted scores), else empty


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


# ------------------------------------------------------------------ hilsim_msgs/action/Move as rosidl derives it
@dataclass
class MoveSendGoalRequest(IdlStruct, typename="hilsim_msgs/action/Move_SendGoal_Request"):
    goal_id: UUID = field(default_factory=UUID)
    goal: MoveGoal = field(default_factory=MoveGoal)


@dataclass
class MoveSendGoalResponse(IdlStruct, typename="hilsim_msgs/action/Move_SendGoal_Response"):
    accepted: bool = False
    stamp: Time = field(default_factory=Time)


@dataclass
class MoveSendGoalEvent(IdlStruct, typename="hilsim_msgs/action/Move_SendGoal_Event"):
    info: ServiceEventInfo = field(default_factory=ServiceEventInfo)
    request: sequence[MoveSendGoalRequest, 1] = field(default_factory=list)
    response: sequence[MoveSendGoalResponse, 1] = field(default_factory=list)


@dataclass
class MoveGetResultRequest(IdlStruct, typename="hilsim_msgs/action/Move_GetResult_Request"):
    goal_id: UUID = field(default_factory=UUID)


@dataclass
class MoveGetResultResponse(IdlStruct, typename="hilsim_msgs/action/Move_GetResult_Response"):
    status: int8 = STATUS_UNKNOWN
    result: MoveResult = field(default_factory=MoveResult)


@dataclass
class MoveGetResultEvent(IdlStruct, typename="hilsim_msgs/action/Move_GetResult_Event"):
    info: ServiceEventInfo = field(default_factory=ServiceEventInfo)
    request: sequence[MoveGetResultRequest, 1] = field(default_factory=list)
    response: sequence[MoveGetResultResponse, 1] = field(default_factory=list)


@dataclass
class MoveFeedbackMessage(IdlStruct, typename="hilsim_msgs/action/Move_FeedbackMessage"):
    goal_id: UUID = field(default_factory=UUID)
    feedback: MoveFeedback = field(default_factory=MoveFeedback)
