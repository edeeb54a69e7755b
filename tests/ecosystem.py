"""Reading memlog's outputs the way other tools do: the mcap reader's decoders (mcap_ros2,
mcap_ros1, mcap_protobuf, json) and rosbags' AnyReader; and turning what they decode back into
memlog's records by the documented conventions (independently of memlog.outputs.channels).

Conventions (README, schemas/): a ROS ``memlog_msgs/FrameScores`` holds NaN for a number not
computed and "" for a missing string, ``has_memorability``/``memorability_rows`` + a row-major
``memorability`` array for the 5x5 matrix (NaN = crop not scored) and ``timing_ms`` as
``StageTime[]``; protobuf leaves missing values unset (proto3 ``optional``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from mcap.decoder import DecoderFactory
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.writer import Writer

FAMILY = {
    "demo.mcap": "ros2", "ros1.bag": "ros1", "ros2_sqlite": "ros2", "ros2_mcap": "ros2",
    "foxglove_json.mcap": "json", "foxglove_proto.mcap": "protobuf", "ros2idl.mcap": "ros2",
    "ros1.mcap": "ros1", "encodings.mcap": "ros2",
}
#: (message encoding, schema encoding) of memlog's channels per family
ENCODINGS = {"ros2": ("cdr", "ros2msg"), "ros1": ("ros1", "ros1msg"), "json": ("json", "jsonschema"),
             "protobuf": ("protobuf", "protobuf")}


class JsonDecoderFactory(DecoderFactory):
    """The mcap reader has no JSON decoder of its own: json.loads for ``json`` channels."""

    def decoder_for(self, message_encoding: str, schema: Schema | None) -> Callable[[bytes], Any] | None:
        return json.loads if message_encoding == "json" else None


def decoder_factory(family: str) -> DecoderFactory:
    """The decoder a user of the mcap reader picks for a file of this family."""
    if family == "ros2":
        from mcap_ros2.decoder import DecoderFactory as Ros2

        return Ros2()
    if family == "ros1":
        from mcap_ros1.decoder import DecoderFactory as Ros1

        return Ros1()
    if family == "protobuf":
        from mcap_protobuf.decoder import DecoderFactory as Protobuf

        return Protobuf()
    return JsonDecoderFactory()


def decoded(path: Path, family: str, topics: set[str] | None = None) -> Iterator[tuple[Schema | None, Channel, Message, Any]]:
    """Every message of ``topics`` (default: all), decoded by the mcap reader with only the decoder
    of ``family`` (mcap_ros2, mcap_ros1, mcap_protobuf or json): a channel it cannot decode raises."""
    with open(path, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True, decoder_factories=[decoder_factory(family)])
        yield from reader.iter_decoded_messages(topics=sorted(topics) if topics is not None else None,
                                                log_time_order=False)


def plain(obj: Any) -> Any:
    """A message decoded by mcap_ros1/mcap_ros2/mcap_protobuf (or JSON) as plain data; times
    (ROS 1 secs/nsecs, ROS 2 sec/nanosec, protobuf Timestamp) as ``{"sec", "nsec"}``."""
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(x) for x in obj]
    if isinstance(obj, (bytes, bytearray, str, int, float, bool)) or obj is None:
        return obj
    desc = getattr(obj, "DESCRIPTOR", None)
    if desc is not None:  # protobuf
        if desc.full_name == "google.protobuf.Timestamp":
            return {"sec": obj.seconds, "nsec": obj.nanos}
        out = {}
        for f in desc.fields:
            v = getattr(obj, f.name)
            rep = f.is_repeated if hasattr(f, "is_repeated") else f.label == f.LABEL_REPEATED
            if not rep and f.has_presence and not obj.HasField(f.name):
                out[f.name] = None
            elif rep:
                out[f.name] = [plain(x) for x in v]
            else:
                out[f.name] = plain(v)
        return out
    slots = getattr(obj, "__slots__", None)
    if slots:
        if set(slots) == {"secs", "nsecs"}:
            return {"sec": obj.secs, "nsec": obj.nsecs}
        if set(slots) == {"sec", "nanosec"}:
            return {"sec": obj.sec, "nsec": obj.nanosec}
        return {s: plain(getattr(obj, s)) for s in slots}
    raise TypeError(f"cannot make plain data of {type(obj)}")


def record_of_scores(msg: dict[str, Any], encoding: str) -> dict[str, Any]:
    """A decoded ``FrameScores`` message (plain data) as memlog's record, by the documented conventions."""
    if encoding == "json":
        return msg
    r = dict(msg)
    if encoding in ("cdr", "ros1"):
        for k in ("ms", "ms_low", "ms_high", "ss", "es"):
            if math.isnan(r[k]):
                r[k] = None
        for k in ("rejected_by", "error"):
            if r[k] == "":
                r[k] = None
    values = [None if math.isnan(v) else v for v in r.pop("memorability")]
    rows = r.pop("memorability_rows")
    if r.pop("has_memorability"):
        cols = len(values) // rows if rows else 0
        r["memorability"] = [values[i * cols:(i + 1) * cols] for i in range(rows)]
    else:
        assert rows == 0 and values == []
        r["memorability"] = None
    r["timing_ms"] = {t["stage"]: t["ms"] for t in r["timing_ms"]}
    return r


def record_of_match(msg: dict[str, Any], encoding: str) -> dict[str, Any]:
    """A decoded ``Match`` message (plain data) as memlog's record: NaN (ROS) is null."""
    r = dict(msg)
    if encoding in ("cdr", "ros1"):
        for k in ("sequence_score", "speed"):
            if math.isnan(r[k]):
                r[k] = None
    return r


def anyreader_read_all(paths: list[Path]) -> dict[str, int]:
    """Open ``paths`` with rosbags' AnyReader, deserialize every message; messages per topic."""
    from rosbags.highlevel import AnyReader

    counts: dict[str, int] = {}
    with AnyReader(paths) as reader:
        for conn, _t, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
    return counts


def anyreader_opens(path: Path) -> bool:
    """Whether rosbags' AnyReader opens ``path`` (a .bag, a bag directory or a ros2 .mcap)."""
    from rosbags.highlevel import AnyReader, AnyReaderError

    try:
        with AnyReader([path]):
            return True
    except AnyReaderError:
        return False


def copy_topics(src: Path, dst: Path, topics: set[str]) -> None:
    """A new MCAP with only ``topics`` of ``src`` (schemas, channels, messages as they are)."""
    with open(src, "rb") as fh, open(dst, "wb") as out:
        r = make_reader(fh)
        w = Writer(out)
        w.start(profile=r.get_header().profile, library="test")
        sids: dict[int, int] = {}
        cids: dict[int, int] = {}
        for schema, channel, message in r.iter_messages(log_time_order=False):
            if channel.topic not in topics:
                continue
            if channel.id not in cids:
                if schema is not None and schema.id not in sids:
                    sids[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
                cids[channel.id] = w.register_channel(channel.topic, channel.message_encoding,
                                                      sids[schema.id] if schema else 0, channel.metadata)
            w.add_message(cids[channel.id], message.log_time, message.data, message.publish_time, message.sequence)
        w.finish()


def ros1_bag_of(src: Path, dst: Path) -> None:
    """The messages of a ros1-profile MCAP as a ROS 1 bag (rosbags' writer; each connection with
    the MCAP schema as its message definition and the channel's md5sum)."""
    from rosbags.rosbag1 import Writer as BagWriter

    with open(src, "rb") as fh, BagWriter(dst) as w:
        conns: dict[int, Any] = {}
        for schema, channel, message in make_reader(fh).iter_messages(log_time_order=True):
            if channel.id not in conns:
                assert schema is not None and schema.encoding == "ros1msg", channel.topic
                pkg, name = schema.name.split("/")
                conns[channel.id] = w.add_connection(channel.topic, f"{pkg}/msg/{name}", msgdef=schema.data.decode(),
                                                     md5sum=channel.metadata["md5sum"])
            w.write(conns[channel.id], message.log_time, message.data)
