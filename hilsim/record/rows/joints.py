"""Joint rows: JointState (truth, measured, commands, controller reference), the robot model's joint
transforms, JointTrajectory (``joint_trajectory``, ``planner/path``) and the robot model itself.

Entity paths:

- ``joints/<joint>/<q>/<source>``: Scalars; q = position | velocity | effort; source = truth
  (``truth/joint_states``), measured (``joint_states``), command (``joint_commands``), reference
  (``controller/reference``), planned (``joint_trajectory`` points at their sim time)
- ``robot/joint_transforms/<joint>``: Transform3D of each moving joint from ``truth/joint_states``,
  every 10 ms of sim time (sent by ``RowWriter.flush``)
- ``robot/<robot name>/…``, ``tf_static``: the URDF model, static (``RobotModel.log_static``)
- ``<trajectory topic>``: TextLog summary; ``<trajectory topic>/joint_space``: LineStrips2D, one
  strip per joint, x = time from start [s] (or waypoint index for paths);
  ``<trajectory topic>/tool_path``: LineStrips3D of the tool in the URDF root frame
"""

from __future__ import annotations

import numpy as np

from hilsim.core import msgs
from hilsim.record.rows.common import COLOURS, MODEL_PERIOD_NS, TIMELINE, RowsBase, part, rr, streams
from hilsim.sim.kinematics import RobotModel

# timed trajectories (a person's, the planner's) and the planner's geometric path
TIMED_TRAJECTORIES = ("joint_trajectory", "planner/joint_trajectory")
TRAJECTORY_TOPICS = (*TIMED_TRAJECTORIES, "planner/path")


class JointRows(RowsBase):
    """The joint rows' methods of :class:`~hilsim.record.rows.writer.RowWriter`."""

    model: RobotModel | None
    _model_rows: dict[str, tuple[list[int], list[float]]]
    _last_model_ns: int | None

    # ------------------------------------------------------------------ static content
    def log_model(self) -> None:
        """The robot model (static) and the frame tool paths are drawn in. If rerun cannot log
        the model, the model's joint transforms are not recorded and its error is raised."""
        m = self.model
        if m is None:
            return
        try:
            for r in streams(self.rec):
                m.log_static(r)
        except Exception:
            m.joints = {}
            raise
        for topic in TRAJECTORY_TOPICS:
            self.rec.log(f"{topic}/tool_path", rr.CoordinateFrame(m.root), static=True)

    def _joint_state(self, root: str, source: str, msg: msgs.JointState, *, model: bool) -> None:
        t = msgs.ns_of(msg.header.stamp)
        names = tuple(msg.name)
        for quantity in ("position", "velocity", "effort"):
            values = getattr(msg, quantity)
            if not values:
                continue
            ck = (root, source, quantity, names)
            entities = self._entity_cache.get(ck)
            if entities is None:
                entities = tuple(f"{root}joints/{part(n)}/{quantity}/{source}" for n in names)
                self._entity_cache[ck] = entities
            self._vector(entities, t, values)
        joints = self.model.joints if self.model is not None else {}
        if model and joints and msg.position:
            last = self._last_model_ns
            if last is None or t - last >= MODEL_PERIOD_NS or t < last:
                self._last_model_ns = t
                for name, v in zip(msg.name, msg.position, strict=False):
                    if name in joints:
                        col = self._model_rows.setdefault(name, ([], []))
                        col[0].append(t)
                        col[1].append(v)
                        self.buffered += 1

    def _trajectory(self, root: str, topic: str, msg: msgs.JointTrajectory) -> None:
        t0 = msgs.ns_of(msg.header.stamp)
        ent = f"{root}{topic}"
        pts = msg.points
        if not pts:
            self._text(ent, t0, "empty trajectory: stop and hold")
            return
        tfs = np.array([msgs.ns_of(p.time_from_start) for p in pts], dtype=np.int64)
        q = np.array([p.positions for p in pts], dtype=float).reshape(len(pts), len(msg.joint_names))
        self._text(
            ent,
            t0,
            f"{len(pts)} points over {tfs[-1] * 1e-9:.3f} s for {', '.join(msg.joint_names)}; "
            f"start {q[0].round(4).tolist()} end {q[-1].round(4).tolist()}",
        )
        # Path waypoints have no meaningful timing: plot them against their index.
        x = tfs * 1e-9 if topic in TIMED_TRAJECTORIES else np.arange(len(pts), dtype=float)
        if topic in TIMED_TRAJECTORIES:
            for i, name in enumerate(msg.joint_names):
                for tf, v in zip(tfs.tolist(), q[:, i].tolist(), strict=True):
                    self._scalar(f"{root}joints/{part(name)}/position/planned", t0 + tf, v)
        self.rec.set_time(TIMELINE, duration=np.timedelta64(t0, "ns"))
        strips = [np.column_stack([x, q[:, i]]) for i in range(q.shape[1])]
        self.rec.log(f"{ent}/joint_space", rr.LineStrips2D(strips, labels=list(msg.joint_names)))
        if self.model is not None and not root:
            tool = self.model.kin.positions(list(msg.joint_names), q)
            self.rec.log(f"{ent}/tool_path", rr.LineStrips3D([tool], colors=[COLOURS["plan"]]))
