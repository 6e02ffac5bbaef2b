"""ROS 2 actions on the wire: unique_identifier_msgs, action_msgs, service_msgs, and the parts of
``control_msgs/action/FollowJointTrajectory`` (control_msgs 5.x, ROS 2 Jazzy) with what they need of
trajectory_msgs and control_msgs.

Field for field the definitions of :mod:`hilsim.core.ros2.types` (tests/test_ros2_types.py checks it).
An action ``A`` travels as rosidl derives it: ``A_SendGoal`` (request: ``goal_id`` + ``A_Goal``; response:
``accepted`` + ``stamp``), ``A_GetResult`` (request: ``goal_id``; response: ``status`` + ``A_Result``),
``action_msgs/srv/CancelGoal``, ``A_FeedbackMessage`` (``goal_id`` + ``A_Feedback``) and
``action_msgs/msg/GoalStatusArray``.
"""

from dataclasses import dataclass, field

from pycdr2 import IdlStruct
from pycdr2.types import array, float64, int8, int32, int64, sequence, uint8, uint16

from hilsim.core.msgs.builtin import Duration, Header, Time
from hilsim.core.msgs.geometry import Transform, Twist
from hilsim.core.msgs.trajectory import JointTrajectory, JointTrajectoryPoint


# ------------------------------------------------------------------ unique_identifier_msgs, action_msgs
@dataclass
class UUID(IdlStruct, typename="unique_identifier_msgs/msg/UUID"):
    """A goal id: 16 bytes (decoded as ``bytes``)."""

    uuid: array[uint8, 16] = field(default_factory=lambda: bytes(16))


@dataclass
class GoalInfo(IdlStruct, typename="action_msgs/msg/GoalInfo"):
    goal_id: UUID = field(default_factory=UUID)
    stamp: Time = field(default_factory=Time)


# action_msgs/msg/GoalStatus.status
STATUS_UNKNOWN = 0
STATUS_ACCEPTED = 1
STATUS_EXECUTING = 2
STATUS_CANCELING = 3
STATUS_SUCCEEDED = 4
STATUS_CANCELED = 5
STATUS_ABORTED = 6


@dataclass
class GoalStatus(IdlStruct, typename="action_msgs/msg/GoalStatus"):
    goal_info: GoalInfo = field(default_factory=GoalInfo)
    status: int8 = STATUS_UNKNOWN


@dataclass
class GoalStatusArray(IdlStruct, typename="action_msgs/msg/GoalStatusArray"):
    status_list: sequence[GoalStatus] = field(default_factory=list)


# action_msgs/srv/CancelGoal response return codes
CANCEL_ERROR_NONE = 0
CANCEL_ERROR_REJECTED = 1
CANCEL_ERROR_UNKNOWN_GOAL_ID = 2
CANCEL_ERROR_GOAL_TERMINATED = 3


@dataclass
class CancelGoalRequest(IdlStruct, typename="action_msgs/srv/CancelGoal_Request"):
    """A zero goal id cancels every goal; a non-zero stamp also every goal accepted at or before it."""

    goal_info: GoalInfo = field(default_factory=GoalInfo)


@dataclass
class CancelGoalResponse(IdlStruct, typename="action_msgs/srv/CancelGoal_Response"):
    return_code: int8 = CANCEL_ERROR_NONE
    goals_canceling: sequence[GoalInfo] = field(default_factory=list)


@dataclass
class ServiceEventInfo(IdlStruct, typename="service_msgs/msg/ServiceEventInfo"):
    """The header of a service's introspection event (``<Srv>_Event``); ``char[16]`` is a uint8 array in IDL."""

    event_type: uint8 = 0
    stamp: Time = field(default_factory=Time)
    client_gid: array[uint8, 16] = field(default_factory=lambda: bytes(16))
    sequence_number: int64 = 0


# ------------------------------------------------------------------ trajectory_msgs (multi-DOF)
@dataclass
class MultiDOFJointTrajectoryPoint(IdlStruct, typename="trajectory_msgs/msg/MultiDOFJointTrajectoryPoint"):
    transforms: sequence[Transform] = field(default_factory=list)
    velocities: sequence[Twist] = field(default_factory=list)
    accelerations: sequence[Twist] = field(default_factory=list)
    time_from_start: Duration = field(default_factory=Duration)


@dataclass
class MultiDOFJointTrajectory(IdlStruct, typename="trajectory_msgs/msg/MultiDOFJointTrajectory"):
    header: Header = field(default_factory=Header)
    joint_names: sequence[str] = field(default_factory=list)
    points: sequence[MultiDOFJointTrajectoryPoint] = field(default_factory=list)


# ------------------------------------------------------------------ control_msgs
@dataclass
class JointTolerance(IdlStruct, typename="control_msgs/msg/JointTolerance"):
    """Per joint: 0 = the controller's default, -1 = no limit, > 0 = the tolerance."""

    name: str = ""
    position: float64 = 0.0
    velocity: float64 = 0.0
    acceleration: float64 = 0.0


@dataclass
class JointComponentTolerance(IdlStruct, typename="control_msgs/msg/JointComponentTolerance"):
    joint_name: str = ""
    component: uint16 = 0
    position: float64 = 0.0
    velocity: float64 = 0.0
    acceleration: float64 = 0.0


# FollowJointTrajectory result error codes
FJT_SUCCESSFUL = 0
FJT_INVALID_GOAL = -1
FJT_INVALID_JOINTS = -2
FJT_OLD_HEADER_TIMESTAMP = -3
FJT_PATH_TOLERANCE_VIOLATED = -4
FJT_GOAL_TOLERANCE_VIOLATED = -5


@dataclass
class FollowJointTrajectoryGoal(IdlStruct, typename="control_msgs/action/FollowJointTrajectory_Goal"):
    trajectory: JointTrajectory = field(default_factory=JointTrajectory)
    multi_dof_trajectory: MultiDOFJointTrajectory = field(default_factory=MultiDOFJointTrajectory)
    path_tolerance: sequence[JointTolerance] = field(default_factory=list)
    component_path_tolerance: sequence[JointComponentTolerance] = field(default_factory=list)
    goal_tolerance: sequence[JointTolerance] = field(default_factory=list)
    component_goal_tolerance: sequence[JointComponentTolerance] = field(default_factory=list)
    goal_time_tolerance: Duration = field(default_factory=Duration)


@dataclass
class FollowJointTrajectoryResult(IdlStruct, typename="control_msgs/action/FollowJointTrajectory_Result"):
    error_code: int32 = FJT_SUCCESSFUL
    error_string: str = ""


@dataclass
class FollowJointTrajectoryFeedback(IdlStruct, typename="control_msgs/action/FollowJointTrajectory_Feedback"):
    header: Header = field(default_factory=Header)
    joint_names: sequence[str] = field(default_factory=list)
    desired: JointTrajectoryPoint = field(default_factory=JointTrajectoryPoint)
    actual: JointTrajectoryPoint = field(default_factory=JointTrajectoryPoint)
    error: JointTrajectoryPoint = field(default_factory=JointTrajectoryPoint)
    multi_dof_joint_names: sequence[str] = field(default_factory=list)
    multi_dof_desired: MultiDOFJointTrajectoryPoint = field(default_factory=MultiDOFJointTrajectoryPoint)
    multi_dof_actual: MultiDOFJointTrajectoryPoint = field(default_factory=MultiDOFJointTrajectoryPoint)
    multi_dof_error: MultiDOFJointTrajectoryPoint = field(default_factory=MultiDOFJointTrajectoryPoint)


@dataclass
class FollowJointTrajectorySendGoalRequest(
    IdlStruct, typename="control_msgs/action/FollowJointTrajectory_SendGoal_Request"
):
    goal_id: UUID = field(default_factory=UUID)
    goal: FollowJointTrajectoryGoal = field(default_factory=FollowJointTrajectoryGoal)


@dataclass
class FollowJointTrajectorySendGoalResponse(
    IdlStruct, typename="control_msgs/action/FollowJointTrajectory_SendGoal_Response"
):
    accepted: bool = False
    stamp: Time = field(default_factory=Time)


@dataclass
class FollowJointTrajectoryGetResultRequest(
    IdlStruct, typename="control_msgs/action/FollowJointTrajectory_GetResult_Request"
):
    goal_id: UUID = field(default_factory=UUID)


@dataclass
class FollowJointTrajectoryGetResultResponse(
    IdlStruct, typename="control_msgs/action/FollowJointTrajectory_GetResult_Response"
):
    status: int8 = STATUS_UNKNOWN
    result: FollowJointTrajectoryResult = field(default_factory=FollowJointTrajectoryResult)


@dataclass
class FollowJointTrajectoryFeedbackMessage(
    IdlStruct, typename="control_msgs/action/FollowJointTrajectory_FeedbackMessage"
):
    goal_id: UUID = field(default_factory=UUID)
    feedback: FollowJointTrajectoryFeedback = field(default_factory=FollowJointTrajectoryFeedback)
