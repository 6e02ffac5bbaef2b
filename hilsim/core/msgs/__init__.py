"""ROS 2 message types, CDR-encoded with pycdr2, plus validation of what arrives.

The field layout of each class follows the ROS 2 ``.msg`` definition, so a ROS 2 node
(e.g. through rmw_zenoh or zenoh-bridge-ros2dds) decodes the bytes as the ROS type named
in ``typename``. A few hilsim-specific action messages (``hilsim_msgs/…``) follow the same
conventions.

:func:`decode` is the only way services turn bytes into messages: it rejects garbage,
truncated payloads, inconsistent array sizes and non-finite numbers with :class:`BadMessage`.

Every name is available here (``from hilsim import msgs; msgs.JointState``); the modules
split them by concern:

- :mod:`~hilsim.core.msgs.builtin` — Time, Duration, Header, Clock and the sim-time helpers
  (:func:`stamp`, :func:`ns_of`, :func:`seconds`, :func:`duration`, :func:`header`);
- :mod:`~hilsim.core.msgs.geometry` — geometry_msgs, tf2_msgs, nav_msgs;
- :mod:`~hilsim.core.msgs.sensor` — sensor_msgs; :mod:`~hilsim.core.msgs.trajectory` — trajectory_msgs;
- :mod:`~hilsim.core.msgs.diagnostics` — diagnostic_msgs and the service log;
- :mod:`~hilsim.core.msgs.contact` — contacts in the physics truth;
- :mod:`~hilsim.core.msgs.parameters` — live parameters; :mod:`~hilsim.core.msgs.action` — the move action
  and its error codes; :mod:`~hilsim.core.msgs.control` — ROS 2 actions on the wire (action_msgs,
  unique_identifier_msgs) and control_msgs' FollowJointTrajectory;
- :mod:`~hilsim.core.msgs.validation` — :class:`BadMessage`, :func:`validate`;
  :mod:`~hilsim.core.msgs.codec` — :func:`encode`, :func:`decode`, :func:`to_dict`, :func:`type_name`;
  :mod:`~hilsim.core.msgs.fastcdr` — the hand-unrolled codec of the per-step types.
"""

from pycdr2 import IdlStruct

from hilsim.core.msgs.action import (
    CANCELED,
    CONTROL_FAILED,
    FAILURE,
    GOAL_IN_COLLISION,
    GOAL_OUT_OF_LIMITS,
    INVALID_GOAL,
    NO_IK_SOLUTION,
    PLANNING_FAILED,
    SUCCESS,
    TIMED_OUT,
    CancelRequest,
    GoalResponse,
    MoveFeedback,
    MoveFeedbackMessage,
    MoveGetResultEvent,
    MoveGetResultRequest,
    MoveGetResultResponse,
    MoveGoal,
    MoveResult,
    MoveSendGoalEvent,
    MoveSendGoalRequest,
    MoveSendGoalResponse,
)
from hilsim.core.msgs.builtin import Clock, Duration, Header, String, Time, duration, header, ns_of, seconds, stamp
from hilsim.core.msgs.codec import decode, encode, encode_reference, prepare, to_dict, type_name
from hilsim.core.msgs.contact import Contact, Contacts
from hilsim.core.msgs.control import (
    UUID,
    CancelGoalRequest,
    CancelGoalResponse,
    FollowJointTrajectoryFeedback,
    FollowJointTrajectoryFeedbackMessage,
    FollowJointTrajectoryGetResultRequest,
    FollowJointTrajectoryGetResultResponse,
    FollowJointTrajectoryGoal,
    FollowJointTrajectoryResult,
    FollowJointTrajectorySendGoalRequest,
    FollowJointTrajectorySendGoalResponse,
    GoalInfo,
    GoalStatus,
    GoalStatusArray,
    JointComponentTolerance,
    JointTolerance,
    MultiDOFJointTrajectory,
    MultiDOFJointTrajectoryPoint,
    ServiceEventInfo,
)
from hilsim.core.msgs.diagnostics import DiagnosticArray, DiagnosticStatus, KeyValue, Log
from hilsim.core.msgs.geometry import (
    MapMetaData,
    OccupancyGrid,
    Odometry,
    Path,
    Point,
    Pose,
    PoseStamped,
    PoseWithCovariance,
    Quaternion,
    TFMessage,
    Transform,
    TransformStamped,
    Twist,
    TwistWithCovariance,
    Vector3,
)
from hilsim.core.msgs.parameters import Parameter, SetParameters, SetParametersResult
from hilsim.core.msgs.sensor import Imu, JointState, LaserScan, NavSatFix, NavSatStatus
from hilsim.core.msgs.trajectory import JointTrajectory, JointTrajectoryPoint
from hilsim.core.msgs.validation import BadMessage, validate

__all__ = [
    "CANCELED",
    "CONTROL_FAILED",
    "FAILURE",
    "GOAL_IN_COLLISION",
    "GOAL_OUT_OF_LIMITS",
    "INVALID_GOAL",
    "NO_IK_SOLUTION",
    "PLANNING_FAILED",
    "SUCCESS",
    "TIMED_OUT",
    "UUID",
    "BadMessage",
    "CancelGoalRequest",
    "CancelGoalResponse",
    "CancelRequest",
    "Clock",
    "Contact",
    "Contacts",
    "DiagnosticArray",
    "DiagnosticStatus",
    "Duration",
    "FollowJointTrajectoryFeedback",
    "FollowJointTrajectoryFeedbackMessage",
    "FollowJointTrajectoryGetResultRequest",
    "FollowJointTrajectoryGetResultResponse",
    "FollowJointTrajectoryGoal",
    "FollowJointTrajectoryResult",
    "FollowJointTrajectorySendGoalRequest",
    "FollowJointTrajectorySendGoalResponse",
    "GoalInfo",
    "GoalResponse",
    "GoalStatus",
    "GoalStatusArray",
    "Header",
    "IdlStruct",
    "Imu",
    "JointComponentTolerance",
    "JointState",
    "JointTolerance",
    "JointTrajectory",
    "JointTrajectoryPoint",
    "KeyValue",
    "LaserScan",
    "Log",
    "MapMetaData",
    "MoveFeedback",
    "MoveFeedbackMessage",
    "MoveGetResultEvent",
    "MoveGetResultRequest",
    "MoveGetResultResponse",
    "MoveGoal",
    "MoveResult",
    "MoveSendGoalEvent",
    "MoveSendGoalRequest",
    "MoveSendGoalResponse",
    "MultiDOFJointTrajectory",
    "MultiDOFJointTrajectoryPoint",
    "NavSatFix",
    "NavSatStatus",
    "OccupancyGrid",
    "Odometry",
    "Parameter",
    "Path",
    "Point",
    "Pose",
    "PoseStamped",
    "PoseWithCovariance",
    "Quaternion",
    "ServiceEventInfo",
    "SetParameters",
    "SetParametersResult",
    "String",
    "TFMessage",
    "Time",
    "Transform",
    "TransformStamped",
    "Twist",
    "TwistWithCovariance",
    "Vector3",
    "decode",
    "duration",
    "encode",
    "encode_reference",
    "header",
    "ns_of",
    "seconds",
    "stamp",
    "to_dict",
    "type_name",
    "validate",
]

prepare(globals().values())
