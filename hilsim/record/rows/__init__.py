"""Decoded hilsim messages as Rerun rows: what the recorder writes for each kind of message.

:class:`RowWriter` turns one message into rows buffered per entity (timeline ``sim_time``, the
message's sim-time stamp) and sends them with ``send_columns`` when :meth:`RowWriter.flush` is
called. The per-step keys (clock, joint states, IMU) have a fast path that skips message objects
(:meth:`RowWriter.raw`, :class:`~hilsim.record.rows.fast._Layout`): the same rows, read from the
payloads' bytes in one numpy pass per batch (``tests/test_rows_fast.py`` holds the two paths to
the same rows).
Entity layout (entities of robots other than the scenario's go under ``robots/<robot>/``):

==============================================  =============================================
``joints/<joint>/<q>/<source>``                 Scalars; q = position | velocity | effort;
                                                source = truth (``truth/joint_states``),
                                                measured (``joint_states``), command
                                                (``joint_commands``), reference
                                                (``controller/reference``), planned
                                                (``joint_trajectory`` points at their sim time);
                                                a fleet sample (``fleet/<topic>``, joints
                                                ``<robot>/<joint>``) robot by robot, under each
                                                robot's root, and then not that robot's own key
``imu/<truth|measured>/<field>/<axis>``         Scalars; field = orientation, angular_velocity,
                                                linear_acceleration
``clock``                                       Scalars: sim time [s]
``sync/<service>``                              Scalars: the acknowledged step [s]
``health/<service>/level`` and ``/<value>``     Scalars (numeric values of the status)
``health/<service>/status``                     TextLog: state and all values
``log/<service>``                               TextLog (rcl_interfaces/Log)
``<planner|navigator>/feedback``, ``…/result``  TextLog, plus ``…/progress`` and
                                                ``…/result/planning_time`` Scalars
``<trajectory topic>``                          TextLog summary (``joint_trajectory``,
                                                ``planner/path``)
``<trajectory topic>/joint_space``              LineStrips2D: one strip per joint, x = time
                                                from start [s] (or waypoint index for paths)
``<trajectory topic>/tool_path``                LineStrips3D of the tool (forward kinematics of
                                                the URDF), in the URDF root frame
``robot/<robot name>/…``, ``tf_static``         the URDF model (``world.urdf``), static
``robot/joint_transforms/<joint>``              Transform3D of each moving joint from
                                                ``truth/joint_states``, every 10 ms of sim time
``world/<geom>``                                the world's static geometry (``hilsim.sim.scene``),
                                                static, frame ``world``
``tf/<child frame>``                            Transform3D parent → child from ``tf`` (every
                                                10 ms of sim time; a transform that did not
                                                change is not repeated); a fixed-base robot:
                                                ``tf/<root link>`` from the world model, static
``scan``                                        Points3D of the finite ranges of ``scan``, in
                                                the scan's frame (its ``header.frame_id``)
``odometry/<q>/<truth|odom>``                   Scalars of ``truth/odom`` and ``odom``; q = x,
                                                y, z, yaw (in the world) and vx, vy, wz (in the
                                                chassis frame)
``paths/<truth|odom>/<k>``                      LineStrips3D: the trail in the world (a point
                                                every 100 ms), ``paths/gps/<k>`` Points3D of
                                                the GPS fixes in the world (with a datum), at
                                                the chassis' true height
``odom/estimate``                               Boxes3D: the chassis where the odometry puts it
``geo/gps/<k>``, ``geo/<truth|odom>/<k>``       GeoPoints of ``gps/fix``; GeoLineStrings of the
                                                truth and odometry trails (with a datum)
``map``, ``plan``                               ``map`` (nav_msgs/OccupancyGrid) as a textured
                                                quad, ``plan`` (nav_msgs/Path) LineStrips3D
``<topic>/<field path>``                        Scalars of any other message type (numeric fields)
``rejected/<key>``, ``errors/<key>``            TextLog of payloads that failed to decode / to
                                                be turned into rows
==============================================  =============================================

The odometry (``odom``, frame ``odom``) is drawn in the world with its frame where the rover
started, as a robot's ``odom`` frame starts where the robot is: the free base's pose in the world
model (:attr:`Scene.base_start`); without a scene, the first ``truth/odom`` if it came before the
first ``odom``, else the world's origin.

Trails and tracks grow with time but stay cheap to write: see :class:`~hilsim.record.rows.mobile._Track`.

The modules, one per message family (each a mixin of :class:`RowWriter`'s methods; the writer
dispatches to them directly, with no layer in between):

=================  ===========================================================================
``common``         what they share: ``part``, the timeline, the world frame, the per-step keys'
                   sources, the row buffers (``_scalar``, ``_vector``, ``_text``)
``writer``         :class:`RowWriter`: its state, ``message`` (dispatch by key and type),
                   ``rejected``/``error``, ``flush``
``fast``           the fast path of clock, joint states and IMU (``raw``, ``learn``, ``drain``)
``joints``         JointState (states, commands, reference), the model's joint transforms,
                   JointTrajectory (``joint_trajectory``, ``planner/path``), the robot model
``imu``            Imu
``mobile``         the rover: odometry, ``tf``, laser scans, GPS fixes, occupancy grid, plan,
                   the world's static scene
``status``         diagnostics (``health/…``) and logs (``log/…``)
``tasks``          planner and navigator results
``generic``        any other message: its numeric fields as scalars
=================  ===========================================================================

Importing this package imports rerun, after turning its analytics off.
"""

from __future__ import annotations

from hilsim.record.rows.common import (
    COLOURS,
    IMU_SOURCES,
    JOINT_SOURCES,
    MODEL_PERIOD_NS,
    TIMELINE,
    WORLD_FRAME,
    Fault,
    part,
    rr,
)
from hilsim.record.rows.fast import IMU_DOUBLES, IMU_VALUES
from hilsim.record.rows.joints import TRAJECTORY_TOPICS
from hilsim.record.rows.mobile import (
    GRID_LIFT,
    GRID_TEXTURE_MAX,
    ODOM_QUANTITIES,
    ODOM_SOURCES,
    PATH_LIFT,
    TRACK_BLOCK,
    TRACK_PERIOD_NS,
    scan_points,
)
from hilsim.record.rows.status import DIAG_LEVELS, LOG_LEVELS, log_level
from hilsim.record.rows.writer import RowWriter

__all__ = [
    "COLOURS",
    "DIAG_LEVELS",
    "GRID_LIFT",
    "GRID_TEXTURE_MAX",
    "IMU_DOUBLES",
    "IMU_SOURCES",
    "IMU_VALUES",
    "JOINT_SOURCES",
    "LOG_LEVELS",
    "MODEL_PERIOD_NS",
    "ODOM_QUANTITIES",
    "ODOM_SOURCES",
    "PATH_LIFT",
    "TIMELINE",
    "TRACK_BLOCK",
    "TRACK_PERIOD_NS",
    "TRAJECTORY_TOPICS",
    "WORLD_FRAME",
    "Fault",
    "RowWriter",
    "log_level",
    "part",
    "rr",
    "scan_points",
]
