"""ROS 2 message types on DDS as the RMWs announce them: names, XTypes type information, type hashes.

A ROS 2 message ``pkg/msg/T`` is the DDS type ``pkg::msg::dds_::T_`` (:func:`dds_struct`, a cyclonedds
``IdlStruct`` generated field for field from :mod:`hilsim.core.ros2.types`). What a DDS implementation
compares before it matches a reader with a writer is more than the name:

- **XTypes type information.** Fast DDS 3 (ROS 2 Kilted) announces every ROS 2 type's TypeObject hash
  and matches a remote endpoint only if it announces the same one. The cyclonedds binding builds the
  TypeObjects itself and gives the element of every sequence and array the flag ``TRY_CONSTRUCT1``;
  rmw_fastrtps gives it none. Structs without collections (``rosgraph_msgs/Clock``) came out identical,
  everything with a ``string[]``, ``float64[]`` or ``float64[9]`` did not, so a Kilted node never received
  ``/<robot>/joint_states`` or ``/<robot>/imu`` (found with both implementations' own traces:
  ``type_information`` in Cyclone's SEDP trace of a Kilted publisher, and Fast DDS's TypeObject of the
  same type fetched with the TypeLookup service). :func:`dds_struct` rewrites the binding's type
  information as Fast DDS writes it (:func:`_fast_dds_type_data`); Fast DDS 2.14 (Jazzy) and Cyclone
  without type information match by name, Cyclone with it by assignability, which the flags do not change.
- **The ROS 2 type hash** (REP 2016) in the endpoint's USER_DATA, ``typehash=RIHS01_<hex>;``, as every
  RMW on DDS writes it (rmw_dds_common): :func:`user_data`. rclpy's ``get_publishers_info_by_topic``
  reads it from there.
"""

from __future__ import annotations

import copy
import hashlib
from functools import cache
from typing import Any

from cyclonedds.idl import IdlStruct, make_idl_struct
from cyclonedds.idl import types as idl
from cyclonedds.idl._support import Endianness
from cyclonedds.idl._typesupport.DDS import XTypes as xt

from hilsim.core.ros2 import types as ros2types

_PRIMITIVE: dict[str, Any] = {
    "bool": bool, "byte": idl.byte, "char": idl.uint8, "int8": idl.int8, "uint8": idl.uint8,
    "int16": idl.int16, "uint16": idl.uint16, "int32": idl.int32, "uint32": idl.uint32,
    "int64": idl.int64, "uint64": idl.uint64, "float32": idl.float32, "float64": idl.float64, "string": str,
}


@cache
def dds_struct(ros_type: str) -> type[IdlStruct]:
    """The cyclonedds type of a ROS 2 message (``nav_msgs/msg/Odometry`` -> ``nav_msgs::msg::dds_::Odometry_``),
    field for field after its definition in :mod:`hilsim.core.ros2.types` (nested types likewise), with
    the XTypes type information Fast DDS announces for it."""
    members: dict[str, Any] = {}
    for f in ros2types.fields(ros_type):
        if f.is_nested:
            t: Any = dds_struct(f.type)
        elif f.type == "string" and f.string_bound:
            t = idl.bounded_str[f.string_bound]
        elif f.type in _PRIMITIVE:
            t = _PRIMITIVE[f.type]
        else:
            raise ValueError(f"{ros_type}.{f.name}: type {f.type} has no DDS mapping here")
        if f.container == "array":
            t = idl.array[t, f.size]
        elif f.container == "sequence":
            t = idl.sequence[t]
        elif f.container == "bounded_sequence":
            t = idl.sequence[t, f.size]
        members[f.name] = t
    if not members:  # rosidl gives an empty struct this member
        members["structure_needs_at_least_one_member"] = idl.uint8
    dds_name = ros2types.dds_type_name(ros_type)
    struct = make_idl_struct(dds_name.rsplit("::", 1)[-1], dds_name, members)
    spec = struct.__idl__
    spec.fill_type_data()
    # the binding hands Cyclone spec._xt_bytedata when a topic is created (clayer/pysertype.c)
    spec._xt_data = _fast_dds_type_data(*spec._xt_data)
    spec._xt_bytedata = tuple(_ser(d) for d in spec._xt_data)
    return struct


def user_data(ros_type: str) -> bytes:
    """An endpoint's USER_DATA as the RMWs on DDS write it: ``typehash=RIHS01_<hex>;``."""
    return f"typehash={ros2types.type_hash(ros_type)};".encode()


def type_ids(ros_type: str) -> tuple[str, str]:
    """(minimal, complete) TypeObject hash of a type as its endpoints announce it, in hex (as Cyclone's
    discovery trace prints them)."""
    info = dds_struct(ros_type).__idl__._xt_data[0]
    return (bytes(info.minimal.typeid_with_size.type_id.value).hex(),
            bytes(info.complete.typeid_with_size.type_id.value).hex())


# ------------------------------------------------------------------------- the type information
def _ser(obj: Any) -> bytes:
    return obj.serialize(endianness=Endianness.Little, use_version_2=True)[4:]


def _fast_dds_type_data(info: Any, mapping: Any) -> tuple[Any, Any]:
    """The binding's (TypeInformation, TypeMapping) with every collection element's flags cleared, as
    Fast DDS builds them, and every hash that depends on them computed again."""
    objects = {bytes(p.type_identifier.value): p.type_object
               for p in [*mapping.identifier_object_pair_minimal, *mapping.identifier_object_pair_complete]}
    renamed: dict[bytes, tuple[Any, Any]] = {}  # old hash -> (new TypeIdentifier, new TypeObject)

    def tid(t: Any) -> Any:
        if t.discriminator in (xt.EK_MINIMAL, xt.EK_COMPLETE):
            return obj_id(bytes(t.value), t.discriminator)
        t = copy.deepcopy(t)
        if t.discriminator in (xt.TI_PLAIN_SEQUENCE_SMALL, xt.TI_PLAIN_SEQUENCE_LARGE,
                               xt.TI_PLAIN_ARRAY_SMALL, xt.TI_PLAIN_ARRAY_LARGE):
            defn = t.value
            defn.header.element_flags = xt.MemberFlag()
            defn.element_identifier = tid(defn.element_identifier)
        elif t.discriminator not in (xt.TI_STRING8_SMALL, xt.TI_STRING8_LARGE) and t.discriminator > xt.TK_CHAR16:
            raise ValueError(f"a ROS 2 message with a type identifier of kind {t.discriminator}")
        return t

    def obj_id(old: bytes, kind: int) -> Any:
        if old not in renamed:
            obj = copy.deepcopy(objects[old])
            body = obj.value.value  # TypeObject -> Minimal/CompleteTypeObject -> its struct type
            if obj.value.discriminator != xt.TK_STRUCTURE:
                raise ValueError(f"a ROS 2 message with a TypeObject of kind {obj.value.discriminator}")
            for m in body.member_seq:
                m.common.member_type_id = tid(m.common.member_type_id)
            new = xt.TypeIdentifier(discriminator=kind, value=hashlib.md5(_ser(obj)).digest()[:14])
            renamed[old] = (new, obj)
        return renamed[old][0]

    def with_deps(deps: Any) -> Any:
        top = obj_id(bytes(deps.typeid_with_size.type_id.value), deps.typeid_with_size.type_id.discriminator)
        dep_ids = [obj_id(bytes(d.type_id.value), d.type_id.discriminator) for d in deps.dependent_typeids]
        size = {bytes(new.value): len(_ser(obj)) for new, obj in renamed.values()}
        return xt.TypeIdentifierWithDependencies(
            typeid_with_size=xt.TypeIdentifierWithSize(type_id=top, typeobject_serialized_size=size[bytes(top.value)]),
            dependent_typeid_count=len(dep_ids),
            dependent_typeids=[xt.TypeIdentifierWithSize(type_id=d, typeobject_serialized_size=size[bytes(d.value)])
                               for d in dep_ids])

    new_info = xt.TypeInformation(minimal=with_deps(info.minimal), complete=with_deps(info.complete))

    def pairs(old_pairs: Any) -> list[Any]:
        return [xt.TypeIdentifierTypeObjectPair(type_identifier=renamed[bytes(p.type_identifier.value)][0],
                                                type_object=renamed[bytes(p.type_identifier.value)][1])
                for p in old_pairs]

    new_map = xt.TypeMapping(
        identifier_object_pair_minimal=pairs(mapping.identifier_object_pair_minimal),
        identifier_object_pair_complete=pairs(mapping.identifier_object_pair_complete),
        identifier_complete_minimal=[
            xt.TypeIdentifierPair(type_identifier1=renamed[bytes(p.type_identifier1.value)][0],
                                  type_identifier2=renamed[bytes(p.type_identifier2.value)][0])
            for p in mapping.identifier_complete_minimal])
    return new_info, new_map
