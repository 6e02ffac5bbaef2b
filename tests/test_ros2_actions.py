"""ROS 2 actions over rmw_zenoh, end to end: a ROS-free action client drives the controller's
``control_msgs/action/FollowJointTrajectory`` and the planner's ``hilsim_msgs/action/Move``.

The client is written here from the specification and shares no code with hilsim's server:

- an action ``<name>`` of type ``<pkg>/action/<A>`` is the services ``<name>/_action/send_goal``
  (``<A>_SendGoal``), ``<name>/_action/cancel_goal`` (``action_msgs/srv/CancelGoal``),
  ``<name>/_action/get_result`` (``<A>_GetResult``) and the topics ``<name>/_action/feedback``
  (``<A>_FeedbackMessage``), ``<name>/_action/status`` (``action_msgs/msg/GoalStatusArray``) (rcl_action);
  the parts rosidl derives are written below (ACTION_PARTS, SERVICE, EVENT);
- a service client (rmw_zenoh's rmw_client_data.cpp) queries ``<domain>/<name>/<pkg>::<kind>::dds_::<Srv>_/<hash>``,
  the hash being the *service* type's (request, response and event), with the request's CDR and the
  33-byte attachment (its own sequence number from 1, the time, its gid: XXH3-128 of its ``SC`` token);
  a reply carries the request's sequence number and the client's gid;
- types, RIHS01 hashes and CDR come from ``rosbags``. Only the texts rosbags does not ship (control_msgs,
  the goal/result/feedback of each action) are taken from hilsim.core.ros2.types, the ROS Jazzy text.

Against real ``hilsim up`` processes: a goal is accepted, feedback flows, the result is SUCCESSFUL and
the arm truly is there (``/arm/truth/joint_states``); invalid goals end with their error codes; a cancel
stops the arm short of the goal.
"""

from __future__ import annotations

import bisect
import itertools
import threading
import time
import uuid
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import xxhash
import zenoh
from ros2_node import DEFAULT_QOS, STORE, Ros2Node, dds_name, mangle
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.msg import get_types_from_msg
from util import UpRun, wait_until
from zenoh.ext import Int64, z_deserialize, z_serialize

from hilsim.core import msgs
from hilsim.core.keys import Keys
from hilsim.core.ros2 import types as hilsim_types

ARM_JOINTS = [f"joint_{i}" for i in range(1, 7)]
FJT = "control_msgs/action/FollowJointTrajectory"
MOVE = "hilsim_msgs/action/Move"
CANCEL_GOAL = "action_msgs/srv/CancelGoal"
# action_msgs/msg/GoalStatus
ACCEPTED, EXECUTING, CANCELING, SUCCEEDED, CANCELED, ABORTED = 1, 2, 3, 4, 5, 6

# ------------------------------------------------------------------ types: rosbags, plus what it lacks
# the parts rosidl derives from an action A (rosidl_parser's Action: goal_id is a UUID, stamp a Time)
ACTION_PARTS = {
    "SendGoal_Request": "unique_identifier_msgs/msg/UUID goal_id\n{A}_Goal goal\n",
    "SendGoal_Response": "bool accepted\nbuiltin_interfaces/msg/Time stamp\n",
    "GetResult_Request": "unique_identifier_msgs/msg/UUID goal_id\n",
    "GetResult_Response": "int8 status\n{A}_Result result\n",
    "FeedbackMessage": "unique_identifier_msgs/msg/UUID goal_id\n{A}_Feedback feedback\n",
}
CANCEL_PARTS = {  # action_msgs/srv/CancelGoal (rosbags ships messages only)
    "Request": "action_msgs/msg/GoalInfo goal_info\n",
    "Response": "int8 return_code\naction_msgs/msg/GoalInfo[] goals_canceling\n",
}
# a service S as rosidl describes it for its type hash (REP 2011): request, response and the event
SERVICE = "{S}_Request request_message\n{S}_Response response_message\n{S}_Event event_message\n"
EVENT = "service_msgs/msg/ServiceEventInfo info\n{S}_Request[<=1] request\n{S}_Response[<=1] response\n"
SEI = "service_msgs/msg/ServiceEventInfo"


def _register(store: Any, name: str, text: str) -> None:
    if name not in store.fielddefs:
        (defs,) = get_types_from_msg(text, name).values()  # (rosbags files pkg/srv/X under another key)
        store.register({name: _srv_names(defs)})


def _srv_names(node: Any) -> Any:
    """rosbags reads a field of type ``pkg/srv/X`` as ``pkg/srv/msg/X``: its real name back."""
    if isinstance(node, str):
        return node.replace("/srv/msg/", "/srv/")
    if isinstance(node, tuple | list):
        return type(node)(_srv_names(n) for n in node)
    return node


PRIMITIVES = {"bool", "byte", "char", "string", "wstring", "float32", "float64",
              *(f"{s}int{n}" for s in ("", "u") for n in (8, 16, 32, 64))}


def _msg_text(text: str, pkg: str) -> str:
    """A bare nested type in an interface file of ``pkg`` is ``pkg/msg/Name`` (rosidl); rosbags would
    look for it next to an action's part (``pkg/action/Name``), so it is written in full."""
    lines = []
    for line in text.splitlines():
        words = line.split(maxsplit=1)
        base = words[0].split("[")[0].split("<")[0] if words else ""
        if words and "/" not in base and base not in PRIMITIVES:
            line = f"{pkg}/msg/{words[0]} {words[1]}"
        lines.append(line)
    return "\n".join(lines) + "\n"


def _action_texts(action: str) -> dict[str, str]:
    """Every message of an action rosbags lacks, by name: the .action's three parts (and the control_msgs
    messages they use), as in hilsim.core.ros2.types, and the parts derived from them, written above."""
    out = {}
    pkg = action.split("/")[0]
    for part in ("Goal", "Result", "Feedback"):
        for dep in hilsim_types.REGISTRY.dependencies(f"{action}_{part}"):
            if dep not in STORE.fielddefs:
                out[dep] = _msg_text(hilsim_types.definition(dep), dep.split("/")[0])
        out[f"{action}_{part}"] = _msg_text(hilsim_types.definition(f"{action}_{part}"), pkg)
    out.update({f"{action}_{p}": t.format(A=action) for p, t in ACTION_PARTS.items()})
    return out


TEXTS = {**_action_texts(FJT), **_action_texts(MOVE), **{f"{CANCEL_GOAL}_{p}": t for p, t in CANCEL_PARTS.items()}}
for _name, _text in TEXTS.items():
    _register(STORE, _name, _text)


def service_hashes() -> dict[str, str]:
    """RIHS01 of each service the clients call, by rosbags from the service's description. rosbags
    hashes ServiceEventInfo's ``char[16]`` as FIELD_TYPE_CHAR where rosidl turns ``char`` into an IDL
    uint8 (tests/test_ros2_types.py), so this store gets the uint8 form of it."""
    store = get_typestore(Stores.EMPTY)
    store.register({k: v for k, v in STORE.fielddefs.items() if k != SEI})
    _register(store, SEI, "uint8 event_type\nbuiltin_interfaces/msg/Time stamp\nuint8[16] client_gid\n"
              "int64 sequence_number\n")
    out = {}
    for srv in (f"{FJT}_SendGoal", f"{FJT}_GetResult", f"{MOVE}_SendGoal", f"{MOVE}_GetResult", CANCEL_GOAL,
                "example_interfaces/action/Fibonacci_SendGoal"):
        _register(store, f"{srv}_Event", EVENT.format(S=srv))
        _register(store, srv, SERVICE.format(S=srv))
        out[srv] = store.hash_rihs01(srv)
    return out


def _fibonacci(store: Any) -> None:
    fib = "example_interfaces/action/Fibonacci"
    for part, text in (("Goal", "int32 order\n"), ("Result", "int32[] sequence\n"), ("Feedback", "int32[] sequence\n")):
        _register(store, f"{fib}_{part}", text)
    for p, t in ACTION_PARTS.items():
        _register(store, f"{fib}_{p}", t.format(A=fib))


_fibonacci(STORE)
SRV_HASH = service_hashes()


def make(ros_type: str, **fields: Any) -> Any:
    """A rosbags message of ``ros_type``: ``fields`` as given, every other field zero / empty."""
    _, defs = STORE.fielddefs[ros_type]
    for fname, (node, arg) in defs:
        if fname not in fields:
            fields[fname] = _default(node, arg)
    return STORE.types[ros_type](**fields)


def _default(node: int, arg: Any) -> Any:
    if node == Nodetype.BASE:
        base = arg[0]
        return "" if base == "string" else False if base == "bool" else 0.0 if base.startswith("float") else 0
    if node == Nodetype.NAME:
        return make(arg)
    (inner, iarg), size = arg
    if inner == Nodetype.BASE and iarg[0] != "string":
        dtype = {"bool": np.bool_, "float64": np.float64, "float32": np.float32}.get(iarg[0], np.dtype(iarg[0]))
        return np.zeros(size if node == Nodetype.ARRAY else 0, dtype=dtype)
    return [_default(inner, iarg) for _ in range(size if node == Nodetype.ARRAY else 0)]


def uuid_msg(goal_id: bytes) -> Any:
    return make("unique_identifier_msgs/msg/UUID", uuid=np.frombuffer(goal_id, dtype=np.uint8).copy())


def duration(s: float) -> Any:
    ns = round(s * 1e9)
    return make("builtin_interfaces/msg/Duration", sec=ns // 10**9, nanosec=ns % 10**9)


# ------------------------------------------------------------------ the client
class ServiceClient:
    """A ROS 2 service client as rmw_zenoh_cpp's (rmw_client_data.cpp): an SC token, queries with the
    33-byte attachment, replies matched by (sequence number, gid)."""

    def __init__(self, node: Ros2Node, service: str, srv_type: str) -> None:
        self.node, self.srv_type = node, srv_type
        hash_ = SRV_HASH[srv_type]
        self.key = f"{node.domain}/{service.strip('/')}/{dds_name(srv_type)}/{hash_}"
        eid = next(node._ids)
        token = (f"@ros2_lv/{node.domain}/{node.zid}/{node.node_id}/{eid}/SC/%/{mangle(node.namespace)}/{node.name}/"
                 f"{mangle(service)}/{dds_name(srv_type)}/{hash_}/{DEFAULT_QOS}")
        self.gid = xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")
        node._decl.append(node.session.liveliness().declare_token(token))
        self._seq = itertools.count(1)
        self._lock = threading.Lock()

    def call(self, request: Any, timeout: float = 15.0) -> Any:
        with self._lock:
            seq = next(self._seq)
        att = z_serialize((Int64(seq), Int64(time.time_ns()), self.gid))
        replies = self.node.session.get(
            self.key, payload=bytes(STORE.serialize_cdr(request, f"{self.srv_type}_Request")), attachment=att,
            target=zenoh.QueryTarget.ALL_COMPLETE, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout)
        for reply in replies:
            assert reply.ok is not None, f"{self.key}: error reply {reply.err.payload.to_string()}"
            rseq, _, rgid = z_deserialize(tuple[Int64, Int64, bytes], reply.ok.attachment)
            assert (int(rseq), bytes(rgid)) == (seq, self.gid), "the reply names another request"
            assert str(reply.ok.key_expr) == self.key
            return STORE.deserialize_cdr(reply.ok.payload.to_bytes(), f"{self.srv_type}_Response")
        raise AssertionError(f"no reply on {self.key} within {timeout} s")

    def call_later(self, request: Any, timeout: float = 120.0) -> dict[str, Any]:
        """Call in a thread (a get_result is answered when the goal ends); the answer lands in the dict."""
        out: dict[str, Any] = {}

        def run() -> None:
            try:
                out["response"] = self.call(request, timeout)
            except BaseException as e:  # reported by the test that waits for it
                out["error"] = e

        t = threading.Thread(target=run, daemon=True)
        t.start()
        out["thread"] = t
        return out


class ActionClient:
    """An action client as rclcpp_action's: goal, get_result right after acceptance, feedback, status, cancel."""

    def __init__(self, node: Ros2Node, name: str, action: str) -> None:
        self.node, self.name, self.action = node, name, action
        self.send_goal = ServiceClient(node, f"{name}/_action/send_goal", f"{action}_SendGoal")
        self.cancel_goal = ServiceClient(node, f"{name}/_action/cancel_goal", CANCEL_GOAL)
        self.get_result = ServiceClient(node, f"{name}/_action/get_result", f"{action}_GetResult")
        self.lock = threading.Lock()
        self.feedback: dict[bytes, list[Any]] = defaultdict(list)
        self.statuses: dict[bytes, list[int]] = defaultdict(list)  # every status seen per goal, in order
        node.subscribe(f"{name}/_action/feedback", f"{action}_FeedbackMessage", self._on_feedback)
        node.subscribe(f"{name}/_action/status", "action_msgs/msg/GoalStatusArray", self._on_status)

    def _on_feedback(self, m: Any, _att: Any) -> None:
        with self.lock:
            self.feedback[bytes(m.goal_id.uuid)].append(m.feedback)

    def _on_status(self, m: Any, _att: Any) -> None:
        with self.lock:
            for st in m.status_list:
                seen = self.statuses[bytes(st.goal_info.goal_id.uuid)]
                if not seen or seen[-1] != st.status:
                    seen.append(int(st.status))

    def server_ready(self) -> bool:
        """The server's three SS tokens (``ros2 action info``), with the types and hashes the client uses."""
        want = {(mangle(f"{self.name}/_action/{s}"), dds_name(t), SRV_HASH[t]) for s, t in (
            ("send_goal", f"{self.action}_SendGoal"), ("cancel_goal", CANCEL_GOAL),
            ("get_result", f"{self.action}_GetResult"))}
        have = {(p[9], p[10], p[11]) for p in self.node.tokens() if p[5] == "SS" and len(p) == 13}
        return want <= have

    def send(self, goal: Any) -> tuple[bytes, Any, dict[str, Any]]:
        goal_id = uuid.uuid4().bytes
        resp = self.send_goal.call(make(f"{self.action}_SendGoal_Request", goal_id=uuid_msg(goal_id), goal=goal))
        result = self.get_result.call_later(make(f"{self.action}_GetResult_Request", goal_id=uuid_msg(goal_id))) \
            if resp.accepted else {}
        return goal_id, resp, result

    def cancel(self, goal_id: bytes) -> Any:
        info = make("action_msgs/msg/GoalInfo", goal_id=uuid_msg(goal_id))
        return self.cancel_goal.call(make(f"{CANCEL_GOAL}_Request", goal_info=info))

    def n_feedback(self, goal_id: bytes) -> int:
        with self.lock:
            return len(self.feedback[goal_id])


def result_of(pending: dict[str, Any], timeout: float = 60.0) -> Any:
    pending["thread"].join(timeout)
    assert "error" not in pending, pending.get("error")
    assert "response" in pending, f"no result within {timeout} s"
    return pending["response"]


class Truth:
    """``/arm/truth/joint_states`` as the node receives it: the latest, and the positions by stamp (a
    loaded machine delivers them late: a result is judged by the truth of its own sim time)."""

    def __init__(self, node: Ros2Node) -> None:
        self.lock = threading.Lock()
        self.last: Any = None
        self.count = 0
        self.stamps: list[int] = []
        self.positions: list[np.ndarray] = []
        node.subscribe("/arm/truth/joint_states", "sensor_msgs/msg/JointState", self._on)

    def _on(self, m: Any, _att: Any) -> None:
        with self.lock:
            self.last, self.count = m, self.count + 1
            self.stamps.append(msgs.ns_of(m.header.stamp))
            self.positions.append(np.array(m.position))

    def at(self, t_ns: int, timeout: float = 15.0) -> np.ndarray:
        """The position of the first sample stamped ``t_ns`` or later, once it has come."""
        def first() -> int | None:
            with self.lock:
                i = bisect.bisect_left(self.stamps, t_ns)
                return i if i < len(self.stamps) else None
        assert wait_until(lambda: first() is not None, timeout), f"no truth stamped {t_ns} ns or later"
        i = first()
        assert i is not None
        with self.lock:
            return self.positions[i]

    def position(self) -> np.ndarray:
        with self.lock:
            return np.array(self.last.position)

    def velocity(self) -> np.ndarray:
        with self.lock:
            return np.array(self.last.velocity)

    def off(self, target: list[float]) -> float:
        return float(np.max(np.abs(self.position() - np.array(target))))


# ------------------------------------------------------------------ without processes
def test_the_clients_keys_agree_with_published_hashes_and_with_hilsim() -> None:
    """The client's own service hashes hit the values published for ROS 2 Jazzy (action_msgs' CancelGoal
    service as rmw_zenoh keys it, example_interfaces' Fibonacci SendGoal), and hilsim's keys are the
    client's: the service type in the key (not the request's), the service's hash."""
    assert SRV_HASH[CANCEL_GOAL] == "RIHS01_573d8b0a534451d7bc2ac8c5ffde8ac14b8593b7001175d0cd6516dcbeb8689a"
    assert SRV_HASH["example_interfaces/action/Fibonacci_SendGoal"] == \
        "RIHS01_d1a57fb2a4afe8c21e34fb10db206f16ce6729b28531141472df92277c55b557"
    assert STORE.hash_rihs01("example_interfaces/action/Fibonacci_FeedbackMessage") == \
        "RIHS01_c1de71afd52e49a89c53d8262366884185bc0a02f78ce051c4e46b0a7fe59bb2"
    for name, action in (("/arm/follow_joint_trajectory", FJT), ("/arm/move", MOVE)):
        ak = Keys().action(name.rsplit("/", 1)[1], action)
        for part, srv in (("send_goal", f"{action}_SendGoal"), ("cancel_goal", CANCEL_GOAL),
                          ("get_result", f"{action}_GetResult")):
            assert getattr(ak, part) == f"0/{name.strip('/')}/_action/{part}/{dds_name(srv)}/{SRV_HASH[srv]}"
        assert ak.feedback == (f"0/{name.strip('/')}/_action/feedback/{dds_name(action + '_FeedbackMessage')}/"
                               f"{STORE.hash_rihs01(action + '_FeedbackMessage')}")
        assert ak.status.endswith("_action/status/action_msgs::msg::dds_::GoalStatusArray_/"
                                  + STORE.hash_rihs01("action_msgs/msg/GoalStatusArray"))
    assert dds_name(f"{FJT}_SendGoal") == "control_msgs::action::dds_::FollowJointTrajectory_SendGoal_"


# ------------------------------------------------------------------ FollowJointTrajectory, end to end
def fjt_goal(points: list[tuple[list[float], float]], names: list[str] = ARM_JOINTS, **extra: Any) -> Any:
    traj = make("trajectory_msgs/msg/JointTrajectory", joint_names=list(names), points=[
        make("trajectory_msgs/msg/JointTrajectoryPoint", positions=np.array(p, float), time_from_start=duration(t))
        for p, t in points])
    return make(f"{FJT}_Goal", trajectory=traj, **extra)


@pytest.mark.e2e
def test_follow_joint_trajectory(router: str, tmp_path: Path) -> None:
    node = Ros2Node(router, name="moveit_controller_manager", namespace="/")
    client = ActionClient(node, "/arm/follow_joint_trajectory", FJT)
    truth = Truth(node)
    run = UpRun(["arm", "--set", "services=[physics,sensors,controller]", "--duration", "120"], router, tmp_path)
    try:
        assert wait_until(client.server_ready, 30), sorted({p[9] for p in node.tokens() if p[5] == "SS"})
        assert wait_until(lambda: truth.count > 50, 30)
        # the QoS rcl_action gives the parts: services and feedback the defaults (reliable, volatile,
        # keep-last 10), the status transient-local keep-last 1
        tokens = {p[9]: (p[8], p[12]) for p in node.tokens() if p[5] in ("MP", "SS") and len(p) == 13}
        ns = "%arm%follow_joint_trajectory%_action%"
        assert tokens.get(f"{ns}feedback") == ("controller", DEFAULT_QOS), tokens
        assert tokens.get(f"{ns}status") == ("controller", ":1:,1:,:,:,,"), tokens
        assert tokens.get(f"{ns}send_goal") == ("controller", DEFAULT_QOS), tokens
        time.sleep(0.5)  # the subscriptions' routes to the controller

        # a goal: accepted, feedback, SUCCESSFUL, and the arm is there
        target = [0.4, -0.3, 0.25, 0.2, 0.35, -0.2]
        gid, resp, pending = client.send(fjt_goal([(target, 1.5)]))
        assert resp.accepted
        result = result_of(pending)
        assert (result.status, result.result.error_code) == (SUCCEEDED, 0), result
        assert wait_until(lambda: client.statuses[gid][-1:] == [SUCCEEDED], 5), client.statuses[gid]
        assert EXECUTING in client.statuses[gid]
        fb = client.feedback[gid]
        # the result came at the step of the last feedback or within one feedback period (20 Hz) after
        # it: the truth of the step after that is at the target (task.tolerance 0.01, measured, + encoder
        # noise)
        after = msgs.ns_of(fb[-1].header.stamp) + 50_000_000
        assert np.max(np.abs(truth.at(after) - target)) < 0.012, truth.at(after)
        assert len(fb) >= 5, len(fb)
        assert list(fb[-1].joint_names) == ARM_JOINTS
        last = fb[-1]
        assert np.allclose(last.error.positions, np.array(last.desired.positions) - last.actual.positions)
        assert np.allclose(fb[0].desired.positions, fb[0].actual.positions, atol=0.05)  # it started from rest
        # a late get_result is answered at once from the kept result
        late = client.get_result.call(make(f"{FJT}_GetResult_Request", goal_id=uuid_msg(gid)))
        assert (late.status, late.result.error_code) == (SUCCEEDED, 0)

        # invalid goals end with their codes and leave the arm where it is
        for goal, code in ((fjt_goal([(target, 1.0)], names=[*ARM_JOINTS[:5], "elbow"]), -2),  # INVALID_JOINTS
                           (fjt_goal([([0.0] * 6, 1.0), ([0.1] * 6, 1.0)]), -1)):  # INVALID_GOAL: times
            _, resp, pending = client.send(goal)
            result = result_of(pending, 15)
            assert (result.status, result.result.error_code) == (ABORTED, code), result
            assert result.result.error_string
        assert truth.off(target) < 0.012

        # a cancel stops the arm short of the goal and holds it there
        home = [0.0] * 6
        gid, resp, pending = client.send(fjt_goal([(home, 6.0)]))
        assert resp.accepted
        start = truth.position()
        assert wait_until(lambda: float(np.max(np.abs(truth.position() - start))) > 0.05, 30)
        cancel = client.cancel(gid)
        assert cancel.return_code == 0 and [bytes(g.goal_id.uuid) for g in cancel.goals_canceling] == [gid]
        result = result_of(pending, 15)
        assert result.status == CANCELED, result
        assert wait_until(lambda: float(np.max(np.abs(truth.velocity()))) < 0.01, 15), truth.velocity()
        held = truth.position()
        time.sleep(1.0)
        assert float(np.max(np.abs(truth.position() - held))) < 0.01, (held, truth.position())
        assert truth.off(home) > 0.1, truth.position()  # stopped short of the goal
        assert client.statuses[gid][-1] == CANCELED
        again = client.cancel(gid)
        assert again.return_code == 3  # ERROR_GOAL_TERMINATED
    finally:
        out = run.stop()
        node.close()
    assert "ready:" in out, out


# ------------------------------------------------------------------ the planner's move action, end to end
def move_goal(joints: list[float]) -> Any:
    return make(f"{MOVE}_Goal", target_kind="joints", joint_names=list(ARM_JOINTS),
                joint_positions=np.array(joints, float), execute=True)


@pytest.mark.e2e
def test_move_action(router: str, tmp_path: Path) -> None:
    node = Ros2Node(router, name="operator", namespace="/")
    client = ActionClient(node, "/arm/move", MOVE)
    truth = Truth(node)
    run = UpRun(["arm", "--set", "services=[physics,sensors,controller,planner]", "--set", "task.targets=[]",
               "--duration", "120"], router, tmp_path)
    try:
        assert wait_until(client.server_ready, 60), sorted({p[9] for p in node.tokens() if p[5] == "SS"})
        assert wait_until(lambda: truth.count > 50, 30)
        time.sleep(0.5)

        left = [0.866, -0.789, -0.399, 0.0, -0.382, 0.0]
        gid, resp, pending = client.send(move_goal(left))
        assert resp.accepted
        result = result_of(pending, 90)
        assert result.status == SUCCEEDED and result.result.success and result.result.error_code == 1, result
        assert result.result.goal_id == str(uuid.UUID(bytes=gid))  # hilsim's id of the action goal
        done = msgs.ns_of(result.result.header.stamp)
        assert np.max(np.abs(truth.at(done) - left)) < 0.012, truth.at(done)  # the truth of the result's step
        states = [f.state for f in client.feedback[gid]]
        assert "planning" in states and "executing" in states, states

        # refused by the planner: aborted with the code of its reason
        _, resp, pending = client.send(move_goal([3.5, 0, 0, 0, 0, 0]))
        result = result_of(pending, 15)
        assert (result.status, result.result.error_code) == (ABORTED, -11), result  # GOAL_OUT_OF_LIMITS
        assert "GOAL_OUT_OF_LIMITS" in result.result.message

        # canceled while executing: the arm brakes to rest on its path, short of the goal
        right = [-0.866, -0.789, -0.399, 0.0, -0.382, 0.0]
        gid, resp, pending = client.send(move_goal(right))
        assert wait_until(lambda: any(f.state == "executing" for f in client.feedback[gid]), 60)
        assert wait_until(lambda: truth.off(left) > 0.1, 30)
        cancel = client.cancel(gid)
        assert cancel.return_code == 0, cancel.return_code
        result = result_of(pending, 15)
        assert (result.status, result.result.error_code) == (CANCELED, -7), result
        assert wait_until(lambda: float(np.max(np.abs(truth.velocity()))) < 0.01, 15), truth.velocity()
        assert truth.off(right) > 0.1, truth.position()
    finally:
        out = run.stop()
        node.close()
    assert "ready:" in out, out
