"""UWB ranging messages found in users' bags, and how each becomes (tag, antenna, anchor, distance) ranges.

There is no standard ROS ranging message. Supported (base names; the package may differ, e.g. a ROS 2 port):

| type | ranges per message | tag / antenna / anchor | stamp |
|---|---|---|---|
| ``uwb_driver/UwbRange`` (NTU-VIRAL) | 1 | requester_id / antenna / responder_id | header |
| ``nlink_parser/LinktrackNodeframe2`` | one per node | frame id / 0 / node id | header, ``stamp`` or bag time |
| ``nlink_parser/LinktrackNodeframe3`` | one per node | frame id / 0 / node id | bag time (no header) |
| ``uwb_msgs/TwoWayRangeStamped`` (aau-cns) | 1 | the non-anchor id / 0 / the id typed 'A' (else id2) | header |
| ``sensor_msgs/Range`` | 1 | 0 / 0 / the number in ``header.frame_id`` | header |

Nooploop's messages exist in several schema versions (with a header and snake_case fields; without a header;
the oldest without a header and with camelCase fields ``node``, ``fpRssi``); the decoders read fields by either
name. The definitions ship as ``.msg`` files under ``convert/msg/<variant>/<package>/``: a ROS 1 bag and a
recent ROS 2 bag carry their own definitions, an older ROS 2 ``.db3`` does not, and then the variant that
decodes the topic's first message exactly (re-encoding gives back its length) is taken.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

MSG_DIR = Path(__file__).with_name("msg")
VARIANTS = ("current", "noheader", "legacy", "ros2port")  # order of the trials on a .db3 without definitions

UWB_DRIVER = "UwbRange"
NODEFRAME2 = "LinktrackNodeframe2"
NODEFRAME3 = "LinktrackNodeframe3"
TWR = "TwoWayRangeStamped"
RANGE = "sensor_msgs/msg/Range"
# base name -> packages it is known under (the type store key is "<package>/msg/<name>")
# base name -> the package it must come from (None: any package, the name is distinctive: the Nooploop types
# are re-packaged in ROS 2 ports and robots' own message packages)
UWB_TYPES = {UWB_DRIVER: "uwb_driver", NODEFRAME2: None, NODEFRAME3: None, TWR: None}


def base_name(msgtype: str) -> str:
    return msgtype.rsplit("/", 1)[-1]


def package(msgtype: str) -> str:
    return msgtype.split("/", 1)[0]


def is_uwb_type(msgtype: str) -> bool:
    """A ranging type this module decodes (sensor_msgs/Range included)."""
    if msgtype in (RANGE, "sensor_msgs/Range"):
        return True
    base = base_name(msgtype)
    return base in UWB_TYPES and UWB_TYPES[base] in (None, package(msgtype))


def ros2_name(msgtype: str) -> str:
    """``pkg/Name`` or ``pkg/msg/Name`` -> ``pkg/msg/Name``."""
    parts = msgtype.split("/")
    return msgtype if len(parts) == 3 else f"{parts[0]}/msg/{parts[-1]}"


@cache
def shipped_definitions(variant: str) -> dict[str, str]:
    """``{"pkg/msg/Name": text}`` of the .msg files of one variant."""
    return {
        f"{f.parent.name}/msg/{f.stem}": f.read_text() for f in sorted((MSG_DIR / variant).glob("*/*.msg"))
    }


def _definitions_for(variant: str, msgtype: str) -> dict[str, str]:
    """The shipped definition of ``msgtype``'s base name (and its nested types) under ``msgtype``'s package."""
    pkg, base = package(msgtype), base_name(msgtype)
    defs = shipped_definitions(variant)
    src = next((n for n in defs if n.endswith(f"/msg/{base}")), None)
    if src is None:
        return {}
    src_pkg = package(src)
    return {f"{pkg}/msg/{base_name(n)}": t for n, t in defs.items() if package(n) == src_pkg}


@cache
def variant_typestore(variant: str, msgtype: str):
    """ROS 2 Humble types plus the shipped definitions of ``variant`` registered under ``msgtype``'s package."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict = {}
    for name, text in _definitions_for(variant, ros2_name(msgtype)).items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def definition_variants(msgtype: str) -> list[str]:
    """Variants that ship a definition of ``msgtype``'s base name, in trial order."""
    return [v for v in VARIANTS if _definitions_for(v, ros2_name(msgtype))]


# ---------------------------------------------------------------------------------------------------------------
# decoding: message object -> ranges
# ---------------------------------------------------------------------------------------------------------------
@dataclass
class Ranges:
    """Ranges decoded from one message (empty lists: the message carried none)."""

    tag: list[int]
    antenna: list[int]
    anchor: list[int]
    distance: list[float]
    stamp_ns: int | None  # None: the message has no stamp of its own (use the bag time)


class Undecodable(Exception):
    """A message of a supported type whose content cannot give a range (reason in the text)."""


def _field(obj: Any, *names: str) -> Any:
    for n in names:
        if hasattr(obj, n):
            return getattr(obj, n)
    raise Undecodable(f"no field {' or '.join(names)}")


def _time_ns(t: Any) -> int:
    sec = getattr(t, "sec", getattr(t, "secs", 0))
    nsec = getattr(t, "nanosec", getattr(t, "nsecs", 0))
    return int(sec) * 1_000_000_000 + int(nsec)


def message_stamp(m: Any) -> int | None:
    """header.stamp, or a top-level ``stamp``; None when absent or zero (unset)."""
    hdr = getattr(m, "header", None)
    t = _time_ns(hdr.stamp) if hdr is not None and hasattr(hdr, "stamp") else None
    if t is None and hasattr(m, "stamp"):
        t = _time_ns(m.stamp)
    return t if t else None


def _uwb_driver(m: Any) -> Ranges:
    return Ranges(
        [int(m.requester_id)], [int(m.antenna)], [int(m.responder_id)], [float(m.distance)], message_stamp(m)
    )


def _nodeframe(m: Any) -> Ranges:
    nodes = _field(m, "nodes", "node")
    tag = int(_field(m, "id"))
    ids = [int(n.id) for n in nodes]
    return Ranges([tag] * len(ids), [0] * len(ids), ids, [float(n.dis) for n in nodes], message_stamp(m))


_ANCHOR = ord("A")


def _twr(m: Any) -> Ranges:
    t1, t2 = int(m.type_id1), int(m.type_id2)
    id1, id2 = int(m.uwb_id1), int(m.uwb_id2)
    if t1 == _ANCHOR and t2 != _ANCHOR:
        tag, anchor = id2, id1
    else:  # id2 typed 'A', or neither/both typed: the destination (slave) is the anchor
        tag, anchor = id1, id2
    return Ranges([tag], [0], [anchor], [float(m.range_raw)], message_stamp(m))


_TRAILING_INT = re.compile(r"(\d+)\D*$")


def anchor_from_frame(frame_id: str) -> int:
    """The anchor id in a sensor_msgs/Range frame_id: its last number ('anchor_3' -> 3, 'uwb/12' -> 12)."""
    m = _TRAILING_INT.search(frame_id or "")
    if m is None:
        raise Undecodable(f"frame_id {frame_id!r} names no anchor id (expected a number, e.g. 'anchor_3')")
    return int(m.group(1))


def _range(m: Any) -> Ranges:
    d = float(m.range)
    lo, hi = float(m.min_range), float(m.max_range)
    if np.isfinite(d) and hi > 0 and not lo <= d <= hi:
        raise Undecodable("range outside [min_range, max_range] (invalid reading, REP 117)")
    return Ranges([0], [0], [anchor_from_frame(m.header.frame_id)], [d], message_stamp(m))


def decoder(msgtype: str) -> Callable[[Any], Ranges]:
    """The function turning a message of ``msgtype`` into ranges."""
    if msgtype in (RANGE, "sensor_msgs/Range"):
        return _range
    return {UWB_DRIVER: _uwb_driver, NODEFRAME2: _nodeframe, NODEFRAME3: _nodeframe, TWR: _twr}[
        base_name(msgtype)
    ]


def decodes_exactly(store, raw: bytes | memoryview, msgtype: str) -> Any | None:
    """The message if ``store`` decodes the CDR bytes and re-encodes them to the same length, else None."""
    try:
        m = store.deserialize_cdr(bytes(raw), msgtype)
        again = store.serialize_cdr(m, msgtype)
    except Exception:  # noqa: BLE001 (any decoder failure means: not this layout)
        return None
    return m if abs(len(again) - len(raw)) < 4 else None
