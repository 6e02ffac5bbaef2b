"""Encoding and decoding: bytes <-> messages.

:func:`decode` is the only way services turn bytes into messages: it rejects garbage,
truncated payloads, inconsistent array sizes and non-finite numbers with
:class:`~hilsim.core.msgs.validation.BadMessage`. The per-step types (Clock, JointState, Imu) go
through the hand-unrolled codec of :mod:`hilsim.core.msgs.fastcdr`, everything else through pycdr2.
"""

import dataclasses
import math
import threading
from collections.abc import Iterable
from typing import Any, TypeVar

from pycdr2 import IdlStruct
from pycdr2._support import Buffer

from hilsim.core.msgs import fastcdr
from hilsim.core.msgs.validation import BadMessage, validate

T = TypeVar("T", bound=IdlStruct)

_local = threading.local()


def _buffer() -> Buffer:
    # pycdr2 encodes every message of a type through one shared buffer by default: threads of
    # one process (zenoh callbacks, health, workers) would corrupt each other's bytes.
    buf = getattr(_local, "buf", None)
    if buf is None:
        buf = _local.buf = Buffer()
    return buf


_LE = fastcdr.HEADER_LE
_FAST_ENCODE, _FAST_DECODE = fastcdr.build()


def encode(msg: IdlStruct) -> bytes:
    fast = _FAST_ENCODE.get(type(msg))
    if fast is not None:
        return fast(msg)
    return msg.serialize(buffer=_buffer())


def encode_reference(msg: IdlStruct) -> bytes:
    """pycdr2's encoding, bypassing the fast path (the reference the fast path is tested against)."""
    return msg.serialize(buffer=_buffer())


def decode(cls: type[T], payload: bytes, *, n_joints: int | None = None) -> T:
    """Decode and validate; raise :class:`BadMessage` with a one-line reason.

    ``n_joints``: for JointState / JointTrajectory, the number of joints expected.
    """
    data = bytes(payload)
    if len(data) < 4:
        # pycdr2 would read an empty buffer as all zeros
        raise BadMessage(f"payload of {len(data)} bytes has no CDR encapsulation header")
    fast = _FAST_DECODE.get(cls)
    try:
        if fast is not None and data[:4] == _LE:
            msg, used = fast(data)
        else:
            buf = Buffer(data, align_offset=4)  # the 4-byte encapsulation header precedes the body
            msg = cls.__idl__.deserialize(buf)  # type: ignore[attr-defined]
            used = buf.tell()
    except Exception as e:  # struct.error, UnicodeDecodeError, IndexError, ValueError, …
        raise BadMessage(f"not a valid {cls.__name__} CDR payload ({len(data)} bytes): {e}") from e
    # More than alignment padding left over means the payload was another (longer) message.
    if len(data) - used >= 4:
        raise BadMessage(f"payload has {len(data)} bytes, a {cls.__name__} of this content has {used}")
    validate(msg, n_joints=n_joints)
    return msg


def to_dict(msg: Any) -> Any:
    """Plain data (for JSON output of ``hilsim topic echo --json``)."""
    if dataclasses.is_dataclass(msg):
        return {f.name: to_dict(getattr(msg, f.name)) for f in dataclasses.fields(msg)}
    if isinstance(msg, list):
        return [to_dict(v) for v in msg]
    if isinstance(msg, float) and not math.isfinite(msg):
        return str(msg)
    return msg


def type_name(cls: type) -> str:
    return cls.__dict__.get("__idl_typename__", cls.__name__).replace("::", "/")


def prepare(objects: Iterable[Any]) -> None:
    """Build pycdr2's per-type machinery now for every message class among ``objects``: its
    lazy first-use set-up is not thread-safe."""
    for obj in list(objects):
        if isinstance(obj, type) and issubclass(obj, IdlStruct) and obj is not IdlStruct:
            obj.deserialize(encode_reference(obj()))
