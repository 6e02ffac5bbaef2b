"""A service as a ROS 2 node on rmw_zenoh: its node in the graph, its endpoints' tokens, its ROS 2 services.

:class:`Ros2Node` is a part of :class:`hilsim.core.service.Service` (which it is mixed into): the
node's ``NN`` graph token, the ``MP``/``MS``/``SS`` tokens of its publishers, subscriptions and service
servers (:mod:`hilsim.core.ros2.wire`, rmw_zenoh's layout), and a ROS 2 service server on Zenoh
queryables (what the action server, :mod:`hilsim.services.ros2_action`, is built of).

Writes: ``@ros2_lv/<domain>/<zid>/<node id>/…`` liveliness tokens; replies on the served
``<domain>/<service>/<type>/<hash>`` keys.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any, TypeVar

import zenoh

from hilsim.core import msgs
from hilsim.core.config import Scenario
from hilsim.core.keys import Keys
from hilsim.core.ros2 import wire

T = TypeVar("T")
# node and entity ids of the ROS 2 graph: unique per Zenoh session, as rmw_zenoh counts them per
# context; one counter per process keeps them unique however many services share a session
_ENTITY_IDS = itertools.count()


class Ros2Node:
    """The ROS 2 side of a service: what it needs of it is below (set by Service)."""

    name: str
    sc: Scenario
    keys: Keys
    session: Any
    lock: Any
    counts_in: Counter[str]
    counts_replied: Counter[str]
    rejected: Counter[str]
    _declared: list[Any]
    _zid: str
    _node_id: int
    log: Any

    def warn(self, text: str) -> None: ...  # Service's

    def fault(self, text: str, exc: BaseException | None = None) -> None: ...  # Service's

    @property
    def node_name(self) -> str:
        """This service as a ROS 2 node: ``controller`` (``motor-model`` is ``motor_model``)."""
        return self.name.split("@")[0].replace("-", "_")

    def graph_token(self, kind: str, key: str, qos: wire.Qos | None = None) -> str:
        """The rmw_zenoh liveliness token of this node's publisher (``MP``) or subscription (``MS``) on a
        concrete data key, as a ROS 2 node on rmw_zenoh_cpp declares it (:mod:`hilsim.core.ros2.wire`)."""
        if qos is None:
            qos = wire.QOS_CLOCK if key == self.keys.clock else wire.QOS_DEFAULT
        return self.keys.entity_token(kind, key, zid=self._zid, node_id=self._node_id, entity_id=next(_ENTITY_IDS),
                                      node=self.node_name, enclave=self.sc.ros2.enclave, qos=qos)

    def declare_node(self, session: Any) -> None:
        """This node's ``NN`` token (the session's Zenoh id and a fresh node id first)."""
        info = getattr(session, "info", None)
        self._zid = str(info.zid()) if info is not None else "1"  # an in-process bus has no Zenoh id
        self._node_id = next(_ENTITY_IDS)
        self._declared.append(session.liveliness().declare_token(wire.node_token(
            self.keys.domain, self._zid, self._node_id, self.sc.ros2.enclave, self.keys.namespace, self.node_name)))

    def ros2_service(
        self,
        name: str,
        srv_type: str,
        req_cls: type[T],
        handler: Callable[[T, Callable[[Any], None]], Any],
    ) -> str:
        """Serve ROS 2 service ``name`` (below the robot's namespace, or absolute) of type ``srv_type``
        (``action_msgs/srv/CancelGoal``, ``control_msgs/action/FollowJointTrajectory_SendGoal``) as a
        node on rmw_zenoh_cpp does: a complete queryable on :meth:`Keys.ros2_service`, a service
        server's graph token (``SS``); each reply carries the response's CDR and an attachment with the
        request's sequence number and client gid (:func:`hilsim.core.ros2.wire.reply_attachment`).

        ``handler(request, reply)`` runs under :attr:`lock` and returns the response message, or None to
        answer later by calling ``reply(response)`` once (an action's get_result waits for its goal's
        end; the query stays open until then). A request that does not decode is answered with an
        error reply. Returns the key."""
        assert self.session is not None
        key = self.keys.ros2_service(name, srv_type)

        def on_query(query: zenoh.Query) -> None:
            self.counts_in[key] += 1
            payload = query.payload.to_bytes() if query.payload is not None else b""
            request_att = query.attachment.to_bytes() if query.attachment is not None else b""
            try:
                req = msgs.decode(req_cls, payload)
            except msgs.BadMessage as e:
                self.rejected[key] += 1
                self.warn(f"rejected request on {key}: {e}")
                query.reply_err(str(e))
                return
            answered = threading.Lock()

            def reply(rep: Any) -> None:
                if not answered.acquire(blocking=False):
                    return  # answered already
                try:
                    att = wire.reply_attachment(request_att, time.time_ns())
                    kw = {} if att is None else {"attachment": att}
                    query.reply(key, msgs.encode(rep), **kw)
                    self.counts_replied[key] += 1
                except zenoh.ZError as e:  # the client or the session went away meanwhile
                    self.log.debug("reply on %s not sent: %s", key, e)
                finally:
                    query.drop()  # the query's end: the client stops waiting for more replies

            try:
                with self.lock:
                    rep = handler(req, reply)
            except Exception as e:
                self.fault(f"error answering {key}: {type(e).__name__}: {e}", exc=e)
                query.reply_err(f"{type(e).__name__}: {e}")
                return
            if rep is not None:
                reply(rep)

        try:
            qable = self.session.declare_queryable(key, on_query, complete=True)
        except TypeError:  # the in-process bus (hilsim.core.inproc) knows no options
            qable = self.session.declare_queryable(key, on_query)
        self._declared.append(qable)
        self._declared.append(self.session.liveliness().declare_token(self.graph_token("SS", key)))
        return key
