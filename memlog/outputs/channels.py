"""memlog's own channels, written in the encoding family of the input log.

A tool that reads the input must be able to read memlog's outputs of it, so every channel memlog
adds follows the input:

=========  =====================  ===================================  ==========================================
family     message encoding       schemas                              used for
=========  =====================  ===================================  ==========================================
ros2       ``cdr``                ``ros2msg`` (full definitions)       ``ros2`` profile (ROS 2 bags, ROS 2 MCAP)
ros1       ``ros1``               ``ros1msg`` + ``md5sum`` metadata    ``ros1`` profile (ROS 1 bags, ROS 1 MCAP)
json       ``json``               ``jsonschema``                       Foxglove JSON MCAP (and mixed inputs)
protobuf   ``protobuf``           ``protobuf`` (FileDescriptorSet)     Foxglove protobuf MCAP
=========  =====================  ===================================  ==========================================

Messages (``kind``): ``memlog.FrameScores`` and ``memlog.Match`` (memlog's, :mod:`memlog.outputs.schemas`),
``foxglove.ImageAnnotations`` (Foxglove's official definitions, vendored) and
``foxglove.CompressedImage`` (``sensor_msgs/CompressedImage`` in ROS). Callers hand over *records*: the
JSON form (the JSON Schemas in ``schemas/``; a CompressedImage record holds ``data`` as bytes), and
:func:`decode_record` turns a message of any family back into that same record.
"""

from __future__ import annotations

import base64
import json
import math
import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields, is_dataclass
from functools import lru_cache
from typing import Any, Callable

import numpy as np

from memlog.io.base import LogReader
from memlog.io.decoders import make_deserializer
from memlog.io.mcap import McapLogWriter
from memlog.io.records import ChannelInfo
from memlog.outputs.schemas import MESSAGES, foxglove_definition, proto_descriptor_set, ros_definition, schema_bytes

__all__ = [
    "FAMILIES", "SCORES", "MATCH", "ANNOTATIONS", "IMAGE",
    "family_of", "MemlogChannels", "decode_record", "RecordDecodeError", "canonical_scores", "canonical_match",
]

FAMILIES = ("ros2", "ros1", "json", "protobuf")
SCORES = "memlog.FrameScores"
MATCH = "memlog.Match"
ANNOTATIONS = "foxglove.ImageAnnotations"
IMAGE = "foxglove.CompressedImage"
KINDS = (SCORES, MATCH, ANNOTATIONS, IMAGE)

_FAMILY_OF_ENCODING = {"cdr": "ros2", "ros1": "ros1", "json": "json", "protobuf": "protobuf"}
_TIME = "builtin_interfaces/msg/Time"


def family_of(reader: LogReader, topics: Iterable[str] | None = None) -> str:
    """The encoding family of ``reader`` for memlog's channels: its profile (ros1, ros2), else the
    message encoding of ``topics`` (default: every channel). Mixed or unknown encodings give json,
    which every MCAP tool reads."""
    if reader.profile in ("ros1", "ros2"):
        return reader.profile
    wanted = None if topics is None else set(topics)
    found = {_FAMILY_OF_ENCODING.get(c.message_encoding, "json")
             for c in reader.channels() if wanted is None or c.topic in wanted}
    return found.pop() if len(found) == 1 else "json"


# -- records <-> the flat message form of memlog's messages ----------------------------------------

_SCORE_FIELDS = ("timestamp", "log_time", "topic", "frame_index", "ms", "ms_low", "ms_high", "ms_exact", "ss", "es",
                 "memorability", "crops_scored", "crops_surrogate", "selected", "rejected_by", "thresholds",
                 "detections", "timing_ms", "error", "shared", "shared_from")
_SCORE_DEFAULTS: dict[str, Any] = {"ms_exact": True, "crops_scored": 0, "crops_surrogate": 0, "detections": 0,
                                   "timing_ms": {}, "topic": "", "shared": False}


def canonical_scores(rec: Mapping[str, Any]) -> dict[str, Any]:
    """A score record with every field of ``memlog.FrameScores`` in schema order (missing optional
    values become null, e.g. the crop matrix a map step dropped), so every encoding holds the same
    record."""
    out = {k: rec.get(k, _SCORE_DEFAULTS.get(k)) for k in _SCORE_FIELDS}
    if out["shared_from"] is None:
        out["shared_from"] = out["frame_index"]
    out["timing_ms"] = dict(out["timing_ms"] or {})
    if out["error"] == "":
        out["error"] = None
    return out


def canonical_match(rec: Mapping[str, Any]) -> dict[str, Any]:
    """A match record with exactly the fields of ``memlog.Match``."""
    return {"timestamp": rec["timestamp"], "frame_index": rec["frame_index"],
            "matches": [{"topic": m["topic"], "frame_index": m["frame_index"], "similarity": m["similarity"]}
                        for m in rec["matches"]],
            "confidence": rec["confidence"], "matched_by": rec.get("matched_by") or "single frame",
            "sequence_score": rec.get("sequence_score"), "speed": rec.get("speed")}


def _scores_to_flat(rec: Mapping[str, Any]) -> dict[str, Any]:
    r = canonical_scores(rec)
    m = r.pop("memorability")
    rows = [list(row) for row in m] if m is not None else []
    if rows and len({len(row) for row in rows}) != 1:
        raise ValueError("the crop memorability matrix is ragged")
    r["has_memorability"] = m is not None
    r["memorability_rows"] = len(rows)
    r["memorability"] = [math.nan if v is None else float(v) for row in rows for v in row]
    r["timing_ms"] = [{"stage": k, "ms": v} for k, v in r["timing_ms"].items()]
    return r


def _scores_from_flat(flat: Mapping[str, Any]) -> dict[str, Any]:
    r = dict(flat)
    values = [None if math.isnan(v) else v for v in r.pop("memorability")]
    n = r.pop("memorability_rows")
    has = r.pop("has_memorability")
    if has and (len(values) % n if n else values):
        raise ValueError(f"memorability: {len(values)} values do not make {n} rows")
    cols = len(values) // n if n else 0
    r["memorability"] = [values[i * cols:(i + 1) * cols] for i in range(n)] if has else None
    r["timing_ms"] = {t["stage"]: t["ms"] for t in r["timing_ms"]}
    return canonical_scores(r)


_FLAT: dict[str, tuple[Callable[[Mapping[str, Any]], dict[str, Any]], Callable[[Mapping[str, Any]], dict[str, Any]]]] = {
    SCORES: (_scores_to_flat, _scores_from_flat),
    MATCH: (canonical_match, canonical_match),
}


def _nullables(kind: str) -> dict[str, str]:
    """Nullable top-level fields of a memlog message and their type (float64 or string)."""
    return {f.name: f.type for f in MESSAGES[kind.removeprefix("memlog.")].fields if f.nullable}


def _image_fields(rec: Mapping[str, Any]) -> tuple[dict[str, int], str, str, bytes]:
    return dict(rec["timestamp"]), str(rec.get("frame_id", "")), str(rec["format"]), bytes(rec["data"])


# -- ROS 1 / ROS 2 -----------------------------------------------------------------------------------

_NUMPY = {"bool": np.bool_, "int8": np.int8, "uint8": np.uint8, "int16": np.int16, "uint16": np.uint16,
          "int32": np.int32, "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64, "float32": np.float32,
          "float64": np.float64, "byte": np.uint8, "char": np.uint8}


def _ros_default(base: str) -> Any:
    if base == "string":
        return ""
    if base == "bool":
        return False
    return 0.0 if base.startswith("float") else 0


def _to_ros(store: Any, typename: str, value: Any) -> Any:
    """A rosbags message of ``typename`` from a record-shaped dict (times as ``{"sec", "nsec"}``;
    missing fields take ROS defaults)."""
    value = value or {}
    if typename == _TIME:
        return store.types[_TIME](sec=int(value.get("sec", 0)), nanosec=int(value.get("nsec", value.get("nanosec", 0))))
    kwargs = {}
    for name, (nodetype, desc) in store.fielddefs[typename][1]:
        v = value.get(name)
        kind = int(nodetype)
        if kind == 1:  # BASE
            kwargs[name] = _ros_default(desc[0]) if v is None else v
        elif kind == 2:  # NAME
            kwargs[name] = _to_ros(store, desc, v)
        else:  # ARRAY (3) or SEQUENCE (4)
            (sub_kind, sub_desc), _ = desc
            items = [] if v is None else v
            if int(sub_kind) == 1 and sub_desc[0] != "string":
                kwargs[name] = np.asarray(items if not isinstance(items, (bytes, bytearray)) else
                                          np.frombuffer(items, np.uint8), dtype=_NUMPY[sub_desc[0]])
            elif int(sub_kind) == 1:
                kwargs[name] = list(items)
            else:
                kwargs[name] = [_to_ros(store, sub_desc, x) for x in items]
    return store.types[typename](**kwargs)


def _from_ros(obj: Any) -> Any:
    """A decoded rosbags (or mcap_ros1/mcap_ros2) message as plain data; times as ``{"sec", "nsec"}``."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (list, tuple)):
        return [_from_ros(x) for x in obj]
    if isinstance(obj, (np.generic,)):
        return obj.item()
    if is_dataclass(obj):
        names = [f.name for f in fields(obj) if not f.name.startswith("_")]
        if set(names) == {"sec", "nanosec"}:
            return {"sec": int(getattr(obj, "sec")), "nsec": int(getattr(obj, "nanosec"))}
        return {n: _from_ros(getattr(obj, n)) for n in names}
    return obj


@lru_cache(maxsize=None)
def _ros_store(family: str) -> Any:
    """A rosbags type store with every type memlog writes for ``family`` (ros1 or ros2)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ver = 1 if family == "ros1" else 2
    store = get_typestore(Stores.EMPTY)
    base = get_typestore(Stores.ROS1_NOETIC if ver == 1 else Stores.ROS2_HUMBLE)
    store.register({k: v for k, v in base.fielddefs.items()
                    if k in ("std_msgs/msg/Header", "sensor_msgs/msg/CompressedImage")})
    for kind in (SCORES, MATCH, ANNOTATIONS):
        name, text = _ros_names(kind, ver)[1], _ros_schema_text(kind, ver)
        store.register(get_types_from_msg(text, name))
    return store


def _ros_names(kind: str, ver: int) -> tuple[str, str]:
    """(MCAP schema name, rosbags type name) of ``kind`` in ROS ``ver``."""
    if kind == IMAGE:
        pkg, short = "sensor_msgs", "CompressedImage"
    elif kind.startswith("foxglove."):
        pkg, short = "foxglove_msgs", kind.removeprefix("foxglove.")
    else:
        pkg, short = "memlog_msgs", kind.removeprefix("memlog.")
    return (f"{pkg}/{short}" if ver == 1 else f"{pkg}/msg/{short}"), f"{pkg}/msg/{short}"


def _ros_schema_text(kind: str, ver: int) -> str:
    if kind.startswith("memlog."):
        return ros_definition(kind.removeprefix("memlog."), ver)
    if kind == IMAGE:
        return str(_ros_store_base(ver).generate_msgdef("sensor_msgs/msg/CompressedImage", ros_version=ver)[0])
    return foxglove_definition(kind, f"ros{ver}msg").decode()


@lru_cache(maxsize=None)
def _ros_store_base(ver: int) -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ver == 1 else Stores.ROS2_HUMBLE)


# -- protobuf ----------------------------------------------------------------------------------------

@lru_cache(maxsize=None)
def _proto_schema(kind: str) -> bytes:
    if kind.startswith("memlog."):
        return proto_descriptor_set(kind.removeprefix("memlog."))
    return foxglove_definition(kind, "protobuf")


@lru_cache(maxsize=None)
def _proto_class(kind: str) -> Any:
    from google.protobuf import descriptor_pb2, descriptor_pool
    from google.protobuf.message_factory import GetMessageClass

    fds = descriptor_pb2.FileDescriptorSet()
    fds.ParseFromString(_proto_schema(kind))
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return GetMessageClass(pool.FindMessageTypeByName(kind))


def _repeated(field: Any) -> bool:
    rep = getattr(field, "is_repeated", None)
    return bool(rep) if rep is not None else bool(field.label == field.LABEL_REPEATED)


def _fill_proto(msg: Any, value: Mapping[str, Any]) -> None:
    """Set the fields of protobuf ``msg`` from a record-shaped dict (None = leave unset)."""
    for f in msg.DESCRIPTOR.fields:
        v = value.get(f.name)
        if v is None:
            continue
        if f.message_type is None:
            if _repeated(f):
                getattr(msg, f.name).extend(v)
            else:
                setattr(msg, f.name, v)
        elif f.message_type.full_name == "google.protobuf.Timestamp":
            ts = getattr(msg, f.name)
            ts.seconds, ts.nanos = int(v.get("sec", 0)), int(v.get("nsec", 0))
        elif _repeated(f):
            for item in v:
                _fill_proto(getattr(msg, f.name).add(), item)
        else:
            _fill_proto(getattr(msg, f.name), v)
            getattr(msg, f.name).SetInParent()


def _from_proto(msg: Any) -> dict[str, Any]:
    """A protobuf message as a record-shaped dict: unset optional fields are None, timestamps
    ``{"sec", "nsec"}``."""
    out: dict[str, Any] = {}
    for f in msg.DESCRIPTOR.fields:
        v = getattr(msg, f.name)
        if f.message_type is not None and f.message_type.full_name == "google.protobuf.Timestamp" and not _repeated(f):
            out[f.name] = {"sec": int(v.seconds), "nsec": int(v.nanos)} if msg.HasField(f.name) else None
        elif _repeated(f):
            out[f.name] = [_from_proto(x) for x in v] if f.message_type is not None else list(v)
        elif f.message_type is not None:
            out[f.name] = _from_proto(v) if msg.HasField(f.name) else None
        elif f.has_presence and not msg.HasField(f.name):
            out[f.name] = None
        else:
            out[f.name] = v
    return out


# -- encoders ----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Codec:
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    metadata: tuple[tuple[str, str], ...]
    encode: Callable[[Mapping[str, Any]], bytes]


def _json_codec(kind: str) -> _Codec:
    def encode(rec: Mapping[str, Any]) -> bytes:
        if kind == IMAGE:
            stamp, frame_id, fmt, data = _image_fields(rec)
            obj: Any = {"timestamp": stamp, "frame_id": frame_id, "format": fmt, "data": base64.b64encode(data).decode()}
        elif kind in _FLAT:
            obj = canonical_scores(rec) if kind == SCORES else canonical_match(rec)
        else:
            obj = rec
        return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()

    return _Codec(kind, "jsonschema", schema_bytes(kind), "json", (), encode)


def _ros_codec(kind: str, family: str) -> _Codec:
    ver = 1 if family == "ros1" else 2
    store = _ros_store(family)
    schema_name, typename = _ros_names(kind, ver)
    serialize = store.serialize_ros1 if ver == 1 else store.serialize_cdr
    nulls = _nullables(kind) if kind in _FLAT else {}

    def encode(rec: Mapping[str, Any]) -> bytes:
        if kind == IMAGE:
            stamp, frame_id, fmt, data = _image_fields(rec)
            header: dict[str, Any] = {"stamp": stamp, "frame_id": frame_id}
            if ver == 1:
                header["seq"] = int(rec.get("seq", 0)) & 0xFFFFFFFF
            value: dict[str, Any] = {"header": header, "format": fmt, "data": data}
        elif kind in _FLAT:
            value = _FLAT[kind][0](rec)
            for name, typ in nulls.items():
                if value[name] is None:
                    value[name] = math.nan if typ == "float64" else ""
        else:
            value = dict(rec)
        return bytes(serialize(_to_ros(store, typename, value), typename))

    text = _ros_schema_text(kind, ver)
    meta: tuple[tuple[str, str], ...] = ()
    if ver == 1:  # ROS 1 tools check the type's md5sum against the connection's
        meta = (("md5sum", str(store.generate_msgdef(typename, ros_version=1)[1])),)
    return _Codec(schema_name, f"ros{ver}msg", text.encode(), "ros1" if ver == 1 else "cdr", meta, encode)


def _proto_codec(kind: str) -> _Codec:
    cls = _proto_class(kind)

    def encode(rec: Mapping[str, Any]) -> bytes:
        msg = cls()
        if kind == IMAGE:
            stamp, frame_id, fmt, data = _image_fields(rec)
            _fill_proto(msg, {"timestamp": stamp, "frame_id": frame_id, "format": fmt, "data": data})
        elif kind in _FLAT:
            _fill_proto(msg, _FLAT[kind][0](rec))
        else:
            _fill_proto(msg, rec)
        return bytes(msg.SerializeToString())

    return _Codec(kind, "protobuf", _proto_schema(kind), "protobuf", (), encode)


@lru_cache(maxsize=None)
def _codec(kind: str, family: str) -> _Codec:
    if kind not in KINDS:
        raise ValueError(f"unknown memlog message {kind!r}")
    if family == "json":
        return _json_codec(kind)
    if family in ("ros1", "ros2"):
        return _ros_codec(kind, family)
    if family == "protobuf":
        return _proto_codec(kind)
    raise ValueError(f"unknown encoding family {family!r} ({', '.join(FAMILIES)})")


class MemlogChannels:
    """memlog's channels on ``writer`` in one encoding ``family``: :meth:`add` registers a topic
    for a message kind (schema and channel once), :meth:`write` encodes a record onto it."""

    def __init__(self, writer: McapLogWriter, family: str) -> None:
        if family not in FAMILIES:
            raise ValueError(f"unknown encoding family {family!r} ({', '.join(FAMILIES)})")
        self.writer, self.family = writer, family
        self._codecs: dict[int, _Codec] = {}

    def add(self, topic: str, kind: str) -> int:
        c = _codec(kind, self.family)
        sid = self.writer.add_schema(c.schema_name, c.schema_encoding, c.schema_data)
        cid = self.writer.add_channel(topic, c.message_encoding, sid, dict(c.metadata))
        self._codecs[cid] = c
        return cid

    def write(self, channel_id: int, log_time: int, record: Mapping[str, Any]) -> None:
        self.writer.write(channel_id, log_time, self._codecs[channel_id].encode(record))


# -- decoding ----------------------------------------------------------------------------------------

@lru_cache(maxsize=64)
def _deserializer(channel: ChannelInfo) -> Callable[[bytes], Any]:
    return make_deserializer(channel)


class RecordDecodeError(ValueError):
    """A memlog message that does not decode (damaged data or a definition that does not fit)."""


def _decode_errors() -> tuple[type[BaseException], ...]:
    from google.protobuf.message import DecodeError
    from rosbags.serde import SerdeError

    return (ValueError, KeyError, TypeError, IndexError, AttributeError, struct.error, UnicodeDecodeError,
            SerdeError, DecodeError)


def decode_record(kind: str, channel: ChannelInfo, data: bytes) -> dict[str, Any]:
    """The record (JSON form) of one ``kind`` message of ``channel``, whatever its encoding.

    Raises :class:`RecordDecodeError` when the message does not decode."""
    if kind not in _FLAT:
        raise ValueError(f"decode_record reads memlog's messages ({', '.join(_FLAT)}), not {kind}")
    try:
        return _decode(kind, channel, data)
    except RecordDecodeError:
        raise
    except _decode_errors() as exc:
        raise RecordDecodeError(f"{type(exc).__name__}: {exc}") from exc


def _decode(kind: str, channel: ChannelInfo, data: bytes) -> dict[str, Any]:
    enc = channel.message_encoding
    decoded = _deserializer(channel)(data)
    if enc == "json":
        if not isinstance(decoded, dict):
            raise RecordDecodeError(f"a {kind} message is a JSON object, not {type(decoded).__name__}")
        return canonical_scores(decoded) if kind == SCORES else canonical_match(decoded)
    if enc == "protobuf":
        flat = _from_proto(decoded)
    elif enc in ("cdr", "ros1"):
        flat = _from_ros(decoded)
        for name, typ in _nullables(kind).items():
            v = flat[name]
            if (typ == "float64" and isinstance(v, float) and math.isnan(v)) or (typ == "string" and v == ""):
                flat[name] = None
    else:
        raise RecordDecodeError(f"message encoding {enc!r} is not one memlog writes")
    return _FLAT[kind][1](flat)
