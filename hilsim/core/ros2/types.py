"""The ROS 2 type descriptions of every interface hilsim puts on the wire, and what is derived from them.

This module reads the ``.msg`` / ``.srv`` / ``.action`` files of ``interfaces/`` (package data, laid
out as ROS packages ship them: ``<package>/<msg|srv|action>/<Name>.<ext>``; ROS 2 Jazzy's, comments
stripped) of the ROS types hilsim uses and of everything they depend on, plus hilsim's own
``hilsim_msgs/…`` types (written field for field after the pycdr2 classes of :mod:`hilsim.core.msgs`).
From those texts it derives:

- the parsed field lists (:func:`fields`, :func:`parse_msg`);
- the REP 2011 type hash ``RIHS01_<sha256>`` (:func:`type_hash`), computed the way
  ``rosidl_generator_type_description`` does: the type description (the type and every type it
  references, sorted by name; default values dropped, constants not part of it) serialized as JSON
  with ``separators=(', ', ': ')`` in the key order of ``type_description_interfaces``, the field
  type ids of ``type_description_interfaces/msg/FieldType``. Services and actions are described as
  rosidl does: a service ``pkg/srv/S`` is a struct of ``request_message``, ``response_message`` and
  ``event_message`` (the synthesised ``S_Event``); an action ``pkg/action/A`` has the parts
  ``A_Goal``, ``A_Result``, ``A_Feedback``, the services ``A_SendGoal`` / ``A_GetResult`` and the
  message ``A_FeedbackMessage``. rmw_zenoh puts the hash of the *service* type (not of its request)
  in a service's key;
- the ``ros2msg`` schema text of rosbag2 / MCAP (:func:`full_definition`);
- the DDS type name rmw implementations use (:func:`dds_type_name`).

It is a leaf module: standard library only, nothing from hilsim, so anything may import it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Literal

__all__ = [
    "Constant",
    "Field",
    "TypeRegistry",
    "dds_type_name",
    "definition",
    "fields",
    "full_definition",
    "is_known",
    "kind",
    "known_types",
    "parse_msg",
    "type_description",
    "type_hash",
]

# ------------------------------------------------------------------------------------ field types
#: ``.msg`` primitive -> its IDL type (rosidl_adapter's MSG_TYPE_TO_IDL: ``char`` is a uint8, ``byte`` an octet)
_MSG_TO_IDL: Final[dict[str, str]] = {
    "bool": "boolean",
    "byte": "octet",
    "char": "uint8",
    "int8": "int8",
    "uint8": "uint8",
    "int16": "int16",
    "uint16": "uint16",
    "int32": "int32",
    "uint32": "uint32",
    "int64": "int64",
    "uint64": "uint64",
    "float32": "float",
    "float64": "double",
    "string": "string",
    "wstring": "wstring",
}
PRIMITIVES: Final[frozenset[str]] = frozenset(_MSG_TO_IDL)

#: type_description_interfaces/msg/FieldType ids of the value types (nested type: 1)
_VALUE_TYPE_ID: Final[dict[str, int]] = {
    "nested": 1,
    "int8": 2,
    "uint8": 3,
    "int16": 4,
    "uint16": 5,
    "int32": 6,
    "uint32": 7,
    "int64": 8,
    "uint64": 9,
    "float": 10,
    "double": 11,
    "long double": 12,
    "char": 13,
    "wchar": 14,
    "boolean": 15,
    "octet": 16,
    "string": 17,
    "wstring": 18,
    "bounded_string": 21,
    "bounded_wstring": 22,
}
#: added to the value type id for a fixed array, a bounded and an unbounded sequence
_CONTAINER_OFFSET: Final[dict[str, int]] = {"": 0, "array": 48, "bounded_sequence": 96, "sequence": 144}

#: the member rosidl gives a struct without fields
_EMPTY_MEMBER: Final = "structure_needs_at_least_one_member"

Container = Literal["", "array", "bounded_sequence", "sequence"]
Kind = Literal["msg", "srv", "action"]


@dataclass(frozen=True)
class Field:
    """One field of a struct. ``type`` is a ``.msg`` primitive (``float64``, ``string``, ``byte``, …) or
    the full name of a nested type (``geometry_msgs/msg/Pose``); ``container`` is ``""`` (a single
    value), ``array`` (``T[size]``), ``bounded_sequence`` (``T[<=size]``) or ``sequence`` (``T[]``);
    ``string_bound`` is N of ``string<=N``; ``default`` the default value text, if any."""

    name: str
    type: str
    container: Container = ""
    size: int = 0
    string_bound: int = 0
    default: str | None = None

    @property
    def is_nested(self) -> bool:
        return self.type not in PRIMITIVES

    def type_id(self) -> int:
        """The ``type_description_interfaces/msg/FieldType`` id."""
        if self.is_nested:
            value = "nested"
        else:
            value = _MSG_TO_IDL[self.type]
            if value in ("string", "wstring") and self.string_bound:
                value = f"bounded_{value}"
        return _VALUE_TYPE_ID[value] + _CONTAINER_OFFSET[self.container]

    def msg_type(self) -> str:
        """The type as written in a ``.msg`` line (nested messages as ``pkg/Name``; a part of a service or
        action, e.g. ``pkg/action/A_Goal`` in ``A_SendGoal_Request``, keeps its full name: ``pkg/A_Goal``
        would name ``pkg/msg/A_Goal``)."""
        base = self.type
        if self.is_nested:
            pkg, kind_, name = base.split("/")
            base = f"{pkg}/{name}" if kind_ == "msg" else base
        elif self.string_bound:
            base = f"{base}<={self.string_bound}"
        suffix = {"": "", "array": f"[{self.size}]", "bounded_sequence": f"[<={self.size}]", "sequence": "[]"}
        return base + suffix[self.container]


@dataclass(frozen=True)
class Constant:
    """A constant line of a ``.msg`` (``int8 STATUS_FIX = 0``): not part of the type description."""

    type: str
    name: str
    value: str


# ---------------------------------------------------------------------------------------- parsing
_NAME_RE: Final = re.compile(r"^[a-zA-Z][a-zA-Z0-9_]*$")
_TYPE_RE: Final = re.compile(r"^(?P<base>[A-Za-z][A-Za-z0-9_/]*)(?:<=(?P<sbound>\d+))?(?:\[(?P<arr>(?:<=)?\d*)\])?$")


def _split_comment(line: str) -> str:
    return line.split("#", 1)[0].strip()


def _resolve(base: str, pkg: str) -> str:
    """A nested type's full name: ``Pose`` -> ``<pkg>/msg/Pose``, ``geometry_msgs/Pose`` ->
    ``geometry_msgs/msg/Pose``; a full ``pkg/kind/Name`` stays."""
    parts = base.split("/")
    if len(parts) == 1:
        return f"{pkg}/msg/{base}"
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and parts[1] in ("msg", "srv", "action"):
        return base
    raise ValueError(f"bad type name {base!r}")


def _parse_type(text: str, pkg: str) -> tuple[str, Container, int, int]:
    m = _TYPE_RE.match(text)
    if m is None:
        raise ValueError(f"bad field type {text!r}")
    base, sbound, arr = m["base"], m["sbound"], m["arr"]
    if sbound is not None and base not in ("string", "wstring"):
        raise ValueError(f"only strings have a bound: {text!r}")
    if base not in PRIMITIVES:
        base = _resolve(base, pkg)
    container: Container = ""
    size = 0
    if arr is not None:
        if arr == "":
            container = "sequence"
        elif arr.startswith("<="):
            container, size = "bounded_sequence", int(arr[2:])
        else:
            container, size = "array", int(arr)
    return base, container, size, int(sbound or 0)


def parse_msg(text: str, pkg: str) -> tuple[tuple[Field, ...], tuple[Constant, ...]]:
    """Parse a ``.msg`` text of package ``pkg`` into its fields and constants.

    Supports primitives, ``string<=N``, ``T[]`` / ``T[N]`` / ``T[<=N]``, nested types with or
    without package (a bare name is in ``pkg``), default values and constants (``T NAME = value``).
    """
    out_fields: list[Field] = []
    constants: list[Constant] = []
    for raw in text.splitlines():
        stripped = raw.strip()
        if not stripped or stripped.startswith("#"):
            continue
        type_text, rest = (*stripped.split(None, 1), "")[:2]
        const = re.match(r"^([A-Za-z][A-Za-z0-9_]*)\s*=\s*(.*)$", rest)
        if const is not None:
            # a string constant's value runs to the end of the line ('#' included), as in rosidl
            value = const[2].strip() if type_text.startswith(("string", "wstring")) else _split_comment(const[2])
            if type_text not in PRIMITIVES:
                raise ValueError(f"a constant must be of a primitive type: {raw!r}")
            constants.append(Constant(type_text, const[1], value))
            continue
        words = _split_comment(stripped).split(None, 2)
        if len(words) < 2 or not _NAME_RE.match(words[1]):
            raise ValueError(f"bad field line {raw!r}")
        base, container, size, sbound = _parse_type(words[0], pkg)
        default = words[2].strip() if len(words) == 3 else None
        out_fields.append(Field(words[1], base, container, size, sbound, default))
    names = [f.name for f in out_fields]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate field names in {names}")
    return tuple(out_fields), tuple(constants)


def _split_sections(text: str, n: int, what: str) -> list[str]:
    sections: list[list[str]] = [[]]
    for line in text.splitlines():
        if line.strip() == "---":
            sections.append([])
        else:
            sections[-1].append(line)
    if len(sections) != n:
        raise ValueError(f"a {what} has {n} parts separated by '---', got {len(sections)}")
    return ["\n".join(s).strip("\n") + "\n" for s in sections]


# --------------------------------------------------------------------------------------- registry
@dataclass(frozen=True)
class _Struct:
    name: str
    kind: Kind  # what the name is: a message, a service or an action
    fields: tuple[Field, ...]
    constants: tuple[Constant, ...]
    text: str | None  # the .msg text of a message (None: a service or an action)


class TypeRegistry:
    """Interface definitions by full name (``pkg/msg/Name``, ``pkg/srv/Name``, ``pkg/action/Name``
    and the parts rosidl synthesises for services and actions)."""

    def __init__(self) -> None:
        self._structs: dict[str, _Struct] = {}
        self._hashes: dict[str, str] = {}

    # ---------------------------------------------------------------- adding
    def add_msg(self, name: str, text: str) -> None:
        """A message ``pkg/msg/Name`` (or a message-like part named ``pkg/action/…``, ``pkg/srv/…``)."""
        pkg, _kind, _short = _split_name(name)
        flds, consts = parse_msg(text, pkg)
        self._put(_Struct(name, "msg", flds, consts, text.strip("\n") + "\n"))

    def add_srv(self, name: str, text: str) -> None:
        """A service ``pkg/srv/Name`` from its ``.srv`` text: the service, ``Name_Request``,
        ``Name_Response`` and ``Name_Event``."""
        request, response = _split_sections(text, 2, "service")
        self._add_service(name, request, response)

    def add_action(self, name: str, text: str) -> None:
        """An action ``pkg/action/Name`` from its ``.action`` text, with every part rosidl derives."""
        if _split_name(name)[1] != "action":
            raise ValueError(f"an action is named pkg/action/Name, not {name!r}")
        goal, result, feedback = _split_sections(text, 3, "action")
        for part, part_text in (("Goal", goal), ("Result", result), ("Feedback", feedback)):
            self.add_msg(f"{name}_{part}", part_text)
        uuid = Field("goal_id", "unique_identifier_msgs/msg/UUID")
        self._add_service(
            f"{name}_SendGoal",
            (uuid, Field("goal", f"{name}_Goal")),
            (Field("accepted", "bool"), Field("stamp", "builtin_interfaces/msg/Time")),
        )
        self._add_service(f"{name}_GetResult", (uuid,), (Field("status", "int8"), Field("result", f"{name}_Result")))
        self._add_synthetic_msg(f"{name}_FeedbackMessage", (uuid, Field("feedback", f"{name}_Feedback")))
        members = (
            Field("goal", f"{name}_Goal"),
            Field("result", f"{name}_Result"),
            Field("feedback", f"{name}_Feedback"),
            Field("send_goal_service", f"{name}_SendGoal"),
            Field("get_result_service", f"{name}_GetResult"),
            Field("feedback_message", f"{name}_FeedbackMessage"),
        )
        self._put(_Struct(name, "action", members, (), None))

    def _add_service(self, name: str, request: str | tuple[Field, ...], response: str | tuple[Field, ...]) -> None:
        for part, body in (("Request", request), ("Response", response)):
            if isinstance(body, str):
                self.add_msg(f"{name}_{part}", body)
            else:
                self._add_synthetic_msg(f"{name}_{part}", body)
        self._add_synthetic_msg(
            f"{name}_Event",
            (
                Field("info", "service_msgs/msg/ServiceEventInfo"),
                Field("request", f"{name}_Request", "bounded_sequence", 1),
                Field("response", f"{name}_Response", "bounded_sequence", 1),
            ),
        )
        members = (
            Field("request_message", f"{name}_Request"),
            Field("response_message", f"{name}_Response"),
            Field("event_message", f"{name}_Event"),
        )
        self._put(_Struct(name, "srv", members, (), None))

    def _add_synthetic_msg(self, name: str, flds: tuple[Field, ...]) -> None:
        text = "".join(f"{f.msg_type()} {f.name}\n" for f in flds)
        self._put(_Struct(name, "msg", flds, (), text))

    def _put(self, struct: _Struct) -> None:
        _split_name(struct.name)
        if not struct.fields and struct.kind == "msg":
            # rosidl gives a struct without fields one uint8 member (on the wire too: one byte)
            struct = dataclasses.replace(struct, fields=(Field(_EMPTY_MEMBER, "uint8"),))
        self._structs[struct.name] = struct
        self._hashes.clear()

    # ---------------------------------------------------------------- queries
    def _get(self, name: str) -> _Struct:
        try:
            return self._structs[name]
        except KeyError:
            raise KeyError(f"unknown ROS 2 type {name!r}") from None

    def names(self) -> tuple[str, ...]:
        return tuple(sorted(self._structs))

    def __contains__(self, name: object) -> bool:
        return name in self._structs

    def kind(self, name: str) -> Kind:
        """``msg`` for a message (also the message parts of services and actions), else ``srv`` / ``action``."""
        return self._get(name).kind

    def fields(self, name: str) -> tuple[Field, ...]:
        """The fields (of an empty message: rosidl's ``structure_needs_at_least_one_member``)."""
        return self._get(name).fields

    def constants(self, name: str) -> tuple[Constant, ...]:
        return self._get(name).constants

    def definition(self, name: str) -> str:
        """The ``.msg`` text of a message type."""
        text = self._get(name).text
        if text is None:
            raise ValueError(f"{name} is a {self.kind(name)}, not a message")
        return text

    def dependencies(self, name: str) -> list[str]:
        """Every type ``name`` references, directly or not, depth first in field order."""
        seen: list[str] = []

        def visit(n: str) -> None:
            for f in self._get(n).fields:
                if f.is_nested and f.type not in seen:
                    seen.append(f.type)
                    visit(f.type)

        visit(name)
        return seen

    def _individual(self, name: str) -> dict[str, Any]:
        flds = self._get(name).fields
        return {
            "type_name": name,
            "fields": [
                {
                    "name": f.name,
                    "type": {
                        "type_id": f.type_id(),
                        "capacity": f.size,
                        "string_capacity": f.string_bound,
                        "nested_type_name": f.type if f.is_nested else "",
                    },
                }
                for f in flds
            ],
        }

    def type_description(self, name: str) -> dict[str, Any]:
        """The hashed form of ``type_description_interfaces/msg/TypeDescription`` (no default values)."""
        return {
            "type_description": self._individual(name),
            "referenced_type_descriptions": [self._individual(n) for n in sorted(self.dependencies(name))],
        }

    def type_hash(self, name: str) -> str:
        """The REP 2011 hash ``RIHS01_<64 hex>`` of a message, service or action type."""
        cached = self._hashes.get(name)
        if cached is None:
            text = json.dumps(
                self.type_description(name),
                separators=(", ", ": "),
                ensure_ascii=True,
                allow_nan=False,
                sort_keys=False,
            )
            cached = self._hashes[name] = "RIHS01_" + hashlib.sha256(text.encode("utf-8")).hexdigest()
        return cached

    def full_definition(self, name: str) -> str:
        """The ``ros2msg`` schema of a message (rosbag2 / MCAP): its ``.msg`` text, then each type it
        depends on after a line of 80 ``=`` and ``MSG: pkg/msg/Name``."""
        parts = [self.definition(name)]
        for dep in self.dependencies(name):
            parts.append("=" * 80 + f"\nMSG: {dep}\n" + self.definition(dep))
        return "".join(parts)


def _split_name(name: str) -> tuple[str, str, str]:
    parts = name.split("/")
    if len(parts) != 3 or parts[1] not in ("msg", "srv", "action") or not all(map(_NAME_RE.match, parts)):
        raise ValueError(f"a ROS 2 type name is pkg/msg|srv|action/Name, not {name!r}")
    return parts[0], parts[1], parts[2]


def dds_type_name(name: str) -> str:
    """The DDS / rmw type name: ``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_``,
    ``action_msgs/srv/CancelGoal`` -> ``action_msgs::srv::dds_::CancelGoal_`` (rmw_zenoh's service type),
    ``control_msgs/action/FollowJointTrajectory_SendGoal_Request`` ->
    ``control_msgs::action::dds_::FollowJointTrajectory_SendGoal_Request_``. ``pkg/Name`` means ``pkg/msg/Name``."""
    parts = name.split("/")
    if len(parts) == 2:
        parts.insert(1, "msg")
    pkg, kind_, short = _split_name("/".join(parts))
    return f"{pkg}::{kind_}::dds_::{short}_"


# ------------------------------------------------------------------------------------ definitions
# The interface files, as ROS packages ship them: interfaces/<package>/<msg|srv|action>/<Name>.<msg|srv|action>.
# ROS 2 Jazzy's (common_interfaces, rcl_interfaces, geometry2, unique_identifier_msgs, control_msgs 5.x), comments
# stripped, names as in the sources (a bare name is in the file's own package); and hilsim's own (hilsim_msgs),
# field for field after the pycdr2 classes of hilsim.core.msgs (same order, same types). Its Move_GoalResponse and
# Move_Cancel (.msg files under action/) belong to hilsim's own goal protocol (the planner's planner/goal and
# planner/cancel queryables); Move.action's goal, result and feedback are also the parts of the ROS 2 action the
# planner serves as /<robot>/move, with every part rosidl derives, so their hashes are those a ROS 2 build of
# hilsim_msgs would give.
INTERFACES_DIR: Final[Path] = Path(__file__).resolve().parent / "interfaces"
_SUFFIX_ORDER: Final[dict[str, int]] = {".msg": 0, ".srv": 1, ".action": 2}  # an action's parts may use messages


#: hilsim's own packages (their types are not in any ROS distribution)
HILSIM_PACKAGES: Final[frozenset[str]] = frozenset({"hilsim_msgs"})


def _default_registry(root: Path = INTERFACES_DIR) -> TypeRegistry:
    """Every interface file under ``root`` (``<package>/<msg|srv|action>/<Name>.<ext>``) in one registry."""
    reg = TypeRegistry()
    files = sorted((f for f in root.glob("*/*/*") if f.suffix in _SUFFIX_ORDER),
                   key=lambda f: (_SUFFIX_ORDER[f.suffix], f.parts[-3] in HILSIM_PACKAGES, str(f)))
    if not files:
        raise RuntimeError(f"no interface files under {root} (the package is installed without its data?)")
    add = {".msg": reg.add_msg, ".srv": reg.add_srv, ".action": reg.add_action}
    for f in files:
        add[f.suffix](f"{f.parts[-3]}/{f.parts[-2]}/{f.stem}", f.read_text())
    missing = {dep for n in reg.names() for f in reg.fields(n) if f.is_nested for dep in [f.type] if dep not in reg}
    if missing:
        raise RuntimeError(f"types referenced but not defined: {sorted(missing)}")
    return reg


#: every type hilsim knows
REGISTRY: Final[TypeRegistry] = _default_registry()


# ----------------------------------------------------------------------------- module-level API
def known_types(kinds: Iterable[Kind] = ("msg", "srv", "action")) -> tuple[str, ...]:
    """Every known type name of the given kinds, sorted (messages include the parts of services and actions)."""
    wanted = set(kinds)
    return tuple(n for n in REGISTRY.names() if REGISTRY.kind(n) in wanted)


def is_known(name: str) -> bool:
    return name in REGISTRY


def kind(name: str) -> Kind:
    return REGISTRY.kind(name)


def fields(name: str) -> tuple[Field, ...]:
    """The parsed fields of a type (of a service / action: its rosidl members)."""
    return REGISTRY.fields(name)


def definition(name: str) -> str:
    """The ``.msg`` text of a message type."""
    return REGISTRY.definition(name)


def type_description(name: str) -> dict[str, Any]:
    return REGISTRY.type_description(name)


def type_hash(name: str) -> str:
    """``RIHS01_<64 hex>`` of a message, service or action type, e.g. ``type_hash("std_msgs/msg/String")``."""
    return REGISTRY.type_hash(name)


def full_definition(name: str) -> str:
    """The ``ros2msg`` schema text of a message type (rosbag2 / MCAP)."""
    return REGISTRY.full_definition(name)
