"""Who may do what on the wire: each identity's rights in a run, derived from the key table.

``hilsim up``'s router gives every process of a run an identity of its own (a Zenoh user and password,
:mod:`hilsim.launch.router`) and lets it do only what this module derives for it from the key table of
:mod:`hilsim.core.keys` (``TOPIC_TABLE``, ``GLOBAL_TABLE``, ``SERVED_TABLE``, ``ACTION_SERVERS``), for the
scenario's services, robots, domain and namespace (docs/security.md, "Who may write what"):

- a **service** (a launch unit: one service, a fleet's ``controller@*``, or a composed ``a+b+c``, whose
  rights are its members' together) may put the topics the table names it a writer of, its own
  ``health``, ``log``, ``sync`` and ``hw/<itself>/joint_states``, ``…/setpoints``; declare its liveliness (``alive``,
  ``lockstep``), its batch key (``logger.batch``; not the recorder) and the ROS 2 graph's tokens; serve
  the queryables and ROS 2 actions the table names it the server of, and ask those it is named an asker
  of. The recorder writes nothing but its own health and log. The ROS 2 bridge to DDS puts, of the topics the
  table gives it (``cmd_vel``, ``joint_trajectory``), only those of its ``from_dds`` (DDS has no identities
  of its own: that list is what every DDS node of the domain may send);
- the **tools** (``hilsim topic``, ``goal``, ``gains``, ``play``, ``ui``; and the ROS 2 nodes given the same
  file) may put what a person is meant to command (``USER`` in the table: ``cmd_vel``,
  ``joint_trajectory``) and the topics no service of this run writes (a run without the sensors: its
  ``joint_states``, e.g. played from a bag), ask the ``USER`` queryables (goals, cancels, gains) and the
  services' ROS 2 actions, and declare ROS 2 graph tokens; never truth, the clock, joint commands, a
  service's health, log or liveliness;
- an **observer** (the launcher, the read-only guest) only reads.

Everybody reads every key and token (subscriptions, liveliness, and the router's deliveries to them):
reading can neither blind nor steer a run. Keys are granted with the robot's chunk a wildcard (every robot
of a fleet; the fleet's processes serve them all) and the type chunks exact, so a key expression put with
wildcards is granted only inside what the identity owns (a put on ``0/**`` matches no grant).

:func:`access_control` turns the rights of every identity into Zenoh's ``access_control`` section (deny by
default, allow rules only: a deny rule cannot stop a put on a wildcard key expression that only intersects
it). Reads and writes no key.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hilsim.core import fleet
from hilsim.core import keys as keyscheme
from hilsim.core.config import ConfigError, Scenario
from hilsim.core.ros2 import types as ros2types
from hilsim.core.ros2 import wire

# What a reader needs, on every key (`**` matches no chunk that starts with '@': the ROS 2 graph, and the
# advanced publishers' caches and detection (transient-local: /tf_static, robot_description), named)
EVERY = ["**", "@ros2_lv/**", "**/@adv/**", "@adv/**"]
ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
                "liveliness_query", "declare_liveliness_subscriber"]
READ_MESSAGES = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]
ACTION_PARTS = ("send_goal", "cancel_goal", "get_result")
# the ROS 2 bridge takes from DDS what a ROS 2 node would send: a user's topics (bridges/ros2_dds.py)
CONFIGURED_WRITES = {"bridge-ros2-dds": "from_dds"}


@dataclass
class Rights:
    """Key expressions one identity may write to: put (and delete), serve (declare a queryable and
    reply), ask (query), declare a liveliness token on."""

    put: set[str] = field(default_factory=set)
    serve: set[str] = field(default_factory=set)
    ask: set[str] = field(default_factory=set)
    tokens: set[str] = field(default_factory=set)

    def __or__(self, other: Rights) -> Rights:
        return Rights(self.put | other.put, self.serve | other.serve, self.ask | other.ask,
                      self.tokens | other.tokens)

    def may_put(self, key: str) -> bool:
        """Whether a put on the concrete ``key`` is granted (a grant includes it, as the router decides)."""
        return _granted(self.put, key)

    def may_ask(self, key: str) -> bool:
        """Whether a query on ``key`` is granted."""
        return _granted(self.ask, key)

    def may_serve(self, key: str) -> bool:
        """Whether a queryable on ``key`` (and its replies) is granted."""
        return _granted(self.serve, key)


def _granted(exprs: set[str], key: str) -> bool:
    import zenoh

    k = zenoh.KeyExpr(key)
    return any(zenoh.KeyExpr(e).includes(k) for e in exprs)


def every_robot(sc: Scenario) -> keyscheme.Keys:
    """The scenario's keys with the robot's chunk a wildcard: every robot's at once."""
    return keyscheme.Keys.of(sc, fleet.ALL)


def _adv(key: str) -> str:
    """What an advanced (transient-local) publisher of ``key`` puts, serves and announces besides it."""
    return f"{key}/@adv/**"


def _action_keys(sc: Scenario, action_type: str) -> tuple[list[str], list[str]]:
    """(its three services, its two topics) of any action of ``action_type``, whatever its name."""
    d = sc.ros2.domain_id

    def service(part: str, srv_type: str) -> str:
        return wire.service_key(d, f"**/_action/{part}", ros2types.dds_type_name(srv_type),
                                ros2types.type_hash(srv_type))

    def topic(part: str, msg_type: str) -> str:
        return wire.topic_key(d, f"**/_action/{part}", ros2types.dds_type_name(msg_type),
                              ros2types.type_hash(msg_type))

    services = [service("send_goal", f"{action_type}_SendGoal"),
                service("cancel_goal", keyscheme.CANCEL_GOAL_SERVICE),
                service("get_result", f"{action_type}_GetResult")]
    topics = [topic("feedback", f"{action_type}_FeedbackMessage"), topic("status", keyscheme.GOAL_STATUS_ARRAY)]
    return services, topics


def _writable(rights: Rights, keys: list[str]) -> None:
    for k in keys:
        rights.put |= {k, _adv(k)}
        # an advanced (transient-local) publisher's cache answers late subscribers: its queryable under @adv,
        # its replies on the key itself
        rights.serve |= {k, _adv(k)}
        rights.tokens.add(_adv(k))


def _common(sc: Scenario) -> Rights:
    """What every process of a run may do besides reading: ask advanced publishers' caches, declare the
    ROS 2 graph's tokens (nodes, publishers, subscriptions, service servers)."""
    return Rights(ask={"**/@adv/**", "@adv/**"}, tokens={wire.graph_key(sc.ros2.domain_id)})


def running(sc: Scenario) -> set[str]:
    """The services a run of ``sc`` starts (base names: ``controller``, not ``controller@arm3``)."""
    return {fleet.split_id(p)[0] for p in sc.processes()}


def service_rights(sc: Scenario, service: str) -> Rights:
    """The rights of one service (base name, or ``<service>@<robot>``; every robot's keys either way)."""
    svc = fleet.split_id(service)[0]
    k = every_robot(sc)
    r = _common(sc)
    mine = configured_writes(sc, svc)  # the DDS bridge: only what it is configured to take from DDS

    def writes(t: str, row: keyscheme.Topic) -> bool:
        return svc in row.writers and (mine is None or t in mine)

    puts = [k.topic(t) for t, row in keyscheme.TOPIC_TABLE.items() if writes(t, row)]
    puts += [getattr(k, t) for t, row in keyscheme.GLOBAL_TABLE.items() if writes(t, row)]
    puts += [k.topic(t) for t in keyscheme.plugin_topics()]  # a plug-in's topics: no writer named, any service's
    puts += [k.health(svc), k.log(svc), k.sync(svc), k.server_state(svc), k.server_setpoints(svc)]  # its own
    _writable(r, puts)
    r.tokens |= {k.alive(svc), f"{sc.prefix}/{fleet.ALL}/lockstep/{svc}/**"}
    records = svc == "logger"
    if not records:  # logger.batch: its batches, and the batching token of the same name
        batches = k.service_batches(svc)  # its own only: the recorder takes from it what the table gives it
        r.put.add(batches)
        r.tokens.add(batches)
    for name, row in keyscheme.SERVED_TABLE.items():
        if row.server == svc:
            r.serve.add(k.service(name))
        if svc in row.askers:
            r.ask.add(k.service(name))
    for action_type, server in keyscheme.ACTION_SERVERS.items():
        if server == svc:
            services, topics = _action_keys(sc, action_type)
            r.serve |= set(services)
            _writable(r, topics)
    return r


def unit_rights(sc: Scenario, unit: str) -> Rights:
    """The rights of a launch unit (one OS process): its members' together (a composed ``a+b+c``)."""
    check_configured_writes(sc)
    out = Rights()
    for m in unit.split("+"):
        out = out | service_rights(sc, m)
    return out


def tools_rights(sc: Scenario) -> Rights:
    """The rights of the run's tools and of the ROS 2 nodes given their file (module docstring)."""
    k = every_robot(sc)
    here = running(sc)
    r = _common(sc)
    puts = []
    for t, row in keyscheme.TOPIC_TABLE.items():
        services = set(row.writers) - {keyscheme.USER}
        # what a person commands, or what nobody in this run writes (joint_states played from a bag into a run
        # without the sensors); never a result: what ends a goal or the run is its service's word only
        if keyscheme.USER in row.writers or (not services & here and not t.endswith("result")):
            puts.append(k.topic(t))
    for t, row in keyscheme.GLOBAL_TABLE.items():
        if not set(row.writers) & here:
            puts.append(getattr(k, t))
    _writable(r, puts)
    r.ask |= {k.service(n) for n, row in keyscheme.SERVED_TABLE.items() if keyscheme.USER in row.askers}
    for action_type in keyscheme.ACTION_SERVERS:
        r.ask |= set(_action_keys(sc, action_type)[0])
    return r


def play_rights(sc: Scenario) -> Rights:
    """``hilsim play``'s own identity: the tools' puts (what a person commands, what no service of the run
    writes), and no query: it replays a bag, it sends no goals nor gains."""
    r = tools_rights(sc)
    r.ask = _common(sc).ask
    return r


def panel_rights(sc: Scenario) -> Rights:
    """The panel's own identity (``hilsim ui``): the tools' queries (goals, cancels, gains, the services'
    ROS 2 actions), and no put: it commands through the services' queryables only."""
    r = tools_rights(sc)
    return Rights(ask=r.ask, tokens=_common(sc).tokens)


# what a lab may hand out: "--may-ask actions" for the services' ROS 2 actions (goals, cancels, results)
ACTIONS = "actions"


def grantable() -> tuple[list[str], list[str]]:
    """(topics a person may command, queryables a person may ask, with ``actions``): what a lab's
    credential may be given (``hilsim creds add``), from the key table."""
    topics = [t for t, row in keyscheme.TOPIC_TABLE.items() if keyscheme.USER in row.writers]
    asks = [n for n, row in keyscheme.SERVED_TABLE.items() if keyscheme.USER in row.askers]
    return topics, [*asks, ACTIONS]


def check_grant(may_write: list[str], may_ask: list[str], where: str = "hilsim creds") -> None:
    """ConfigError (one line) for a topic or queryable a person may not be given (the key table's)."""
    topics, asks = grantable()
    for t in may_write:
        if t not in topics:
            row = keyscheme.TOPIC_TABLE.get(t) or keyscheme.GLOBAL_TABLE.get(t)
            who = f"written by {', '.join(row.writers)} only" if row is not None else "not in the key table"
            raise ConfigError(f"{where}: --may-write {t}: {who} (docs/keys.md); a credential may write "
                              + ", ".join(topics))
    for n in may_ask:
        if n not in asks:
            raise ConfigError(f"{where}: --may-ask {n}: not a queryable a person may ask; one of " + ", ".join(asks))


def grant_rights(sc: Scenario, may_write: list[str], may_ask: list[str]) -> Rights:
    """The rights of a lab's credential (``hilsim creds add``): put only ``may_write`` (every robot's), ask
    only ``may_ask`` (and the services' actions with ``actions``), declare ROS 2 graph tokens."""
    check_grant(may_write, may_ask)
    k = every_robot(sc)
    r = _common(sc)
    _writable(r, [k.topic(t) for t in may_write])
    r.ask |= {k.service(n) for n in may_ask if n != ACTIONS}
    if ACTIONS in may_ask:
        for action_type in keyscheme.ACTION_SERVERS:
            r.ask |= set(_action_keys(sc, action_type)[0])
    return r


def owners(sc: Scenario, topic: str) -> list[str]:
    """The services of this run that the table names writers of ``topic`` (relative, ``joint_states``;
    global ``clock``); empty when none runs (then the tools may write it)."""
    row = keyscheme.TOPIC_TABLE.get(topic) or keyscheme.GLOBAL_TABLE.get(topic)
    if row is None:
        return []
    here = running(sc)
    return [w for w in row.writers if w in here]


def configured_writes(sc: Scenario, service: str) -> set[str] | None:
    """The topics of the table that ``service`` (base name) may put in this run: for a service whose
    configuration names what it writes (``CONFIGURED_WRITES``: the ROS 2 bridge's ``from_dds``) those it
    names, when it names them (unset: the service's default, every topic the table gives it); for any other,
    every topic the table gives it (None)."""
    fieldname = CONFIGURED_WRITES.get(service)
    names = sc.section(service).get(fieldname) if fieldname is not None else None
    return {str(n).strip("/") for n in names} if isinstance(names, list) else None


def check_configured_writes(sc: Scenario) -> None:
    """A service whose configuration names the topics it writes (the ROS 2 bridge's ``from_dds``) may
    write only what the table grants it: ConfigError (one line) for any other."""
    for svc, fieldname in CONFIGURED_WRITES.items():
        if svc not in running(sc):
            continue
        names = sc.section(svc).get(fieldname)
        if names is None:
            continue
        for name in names if isinstance(names, list) else []:
            bare = str(name).strip("/")
            row = keyscheme.TOPIC_TABLE.get(bare) or keyscheme.GLOBAL_TABLE.get(bare)
            if row is not None and svc not in row.writers:
                who = ", ".join(row.writers)
                raise ConfigError(f"{sc.source or 'scenario'}: {svc}.{fieldname}: {name}: written by {who} "
                                  f"(the key table, docs/keys.md); {svc} may write only "
                                  + ", ".join(t for t, r in keyscheme.TOPIC_TABLE.items() if svc in r.writers))


def access_control(identities: dict[str, Rights | None]) -> dict[str, Any]:
    """Zenoh's ``access_control`` section for a router whose users are ``identities`` (username -> its
    rights; None: read only). Deny by default; everybody may read everything (and be delivered it)."""
    rules: list[dict[str, Any]] = [
        {"id": "read", "messages": READ_MESSAGES, "flows": ["ingress"], "permission": "allow", "key_exprs": EVERY},
        {"id": "deliver", "messages": ALL_MESSAGES, "flows": ["egress"], "permission": "allow", "key_exprs": EVERY},
    ]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for i, (user, rights) in enumerate(identities.items()):
        sid = f"s{i}"
        subjects.append({"id": sid, "usernames": [user]})
        mine = ["read", "deliver"]
        if rights is not None:
            for what, messages, exprs in (("put", ["put", "delete"], rights.put),
                                          ("serve", ["declare_queryable", "reply"], rights.serve),
                                          ("ask", ["query"], rights.ask),
                                          ("tokens", ["liveliness_token"], rights.tokens)):
                if exprs:
                    rid = f"{sid} {what}"
                    rules.append({"id": rid, "messages": messages, "flows": ["ingress"], "permission": "allow",
                                  "key_exprs": sorted(exprs)})
                    mine.append(rid)
        policies.append({"id": f"{user}", "rules": mine, "subjects": [sid]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}
