"""Deserialize messages from the schema carried in the log (no ROS install needed).

ROS 1 and ROS 2 messages are decoded with rosbags, whose type system builds message
classes from ``.msg`` and ``.idl`` definitions, so custom or newer definitions work. JSON
messages are parsed with :mod:`json`, protobuf messages with the descriptors in the schema.
When a log carries no definition (old ROS 2 bags), rosbags' built-in Humble / Noetic
type stores are used.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from typing import Any

from memlog.io.records import ChannelInfo

__all__ = ["make_deserializer", "UnsupportedEncoding"]

Deserializer = Callable[[bytes], Any]


class UnsupportedEncoding(ValueError):
    """The channel's message or schema encoding cannot be decoded by memlog."""


def _typestore_from_definition(name: str, text: str, schema_encoding: str) -> Any:
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    if schema_encoding == "ros2idl":
        # MCAP ros2idl: the main IDL, then each dependency after a line of '=' and "IDL: pkg/msg/Name"
        types = {}
        for section in re.split(r"^=+\s*$", text, flags=re.M):
            body = "\n".join(line for line in section.splitlines() if not line.startswith("IDL: "))
            if body.strip():
                types.update(get_types_from_idl(body))
    else:
        types = get_types_from_msg(text, name)
    store.register(types)
    return store


def _builtin_typestore(ros_version: int) -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros_version == 1 else Stores.ROS2_HUMBLE)


def _ros_typename(name: str) -> str:
    """ROS 1 names (``sensor_msgs/Image``) as rosbags spells them (``sensor_msgs/msg/Image``)."""
    parts = name.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name.replace("::", "/")


def make_deserializer(channel: ChannelInfo) -> Deserializer:
    """A function that turns one serialized message of ``channel`` into an object.

    Raises :class:`UnsupportedEncoding` when the encoding is unknown or the schema does not
    parse (the message says which).
    """
    enc = channel.message_encoding
    schema = channel.schema
    if enc == "json":
        return lambda data: json.loads(data)
    if enc == "protobuf":
        if schema is None:
            raise UnsupportedEncoding("protobuf channel without a schema")
        from mcap.records import Schema
        from mcap_protobuf.decoder import DecoderFactory

        rec = Schema(id=1, name=schema.name, encoding=schema.encoding, data=schema.data)
        dec = DecoderFactory().decoder_for("protobuf", rec)
        if dec is None:
            raise UnsupportedEncoding(f"protobuf schema {schema.name} does not load")
        return dec
    if enc in ("cdr", "ros1"):
        ros_version = 1 if enc == "ros1" else 2
        if schema is None or not schema.name:
            raise UnsupportedEncoding(f"{enc} channel without a message type")
        typename = _ros_typename(schema.name)
        text = schema.data.decode("utf-8", errors="replace") if schema.data else ""
        try:
            store = (
                _typestore_from_definition(typename, text, schema.encoding)
                if text.strip()
                else _builtin_typestore(ros_version)
            )
        except Exception as exc:  # rosbags raises several parser errors
            raise UnsupportedEncoding(f"message definition of {schema.name} does not parse: {exc}") from exc
        if schema.encoding == "ros2idl":
            # IDL names use '::'; rosbags registers them as pkg/msg/Name
            typename = typename.replace("::", "/")
        if typename not in store.types:
            raise UnsupportedEncoding(f"definition for {schema.name} has no type {typename}")
        if ros_version == 1:
            return lambda data: store.deserialize_ros1(data, typename)
        return lambda data: store.deserialize_cdr(data, typename)
    raise UnsupportedEncoding(f"message encoding {enc!r} is not supported")
