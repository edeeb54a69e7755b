"""Definitions of every channel memlog writes, in every encoding family.

memlog's own messages (``memlog.FrameScores``, ``memlog.Match``) are defined here twice:

* as JSON Schemas (:data:`FRAME_SCORES`, :data:`MATCH`): the *record* form, which is what
  :func:`memlog.outputs.annotated.read_scores` returns whatever the encoding (``null`` = not computed);
* as message specs (:data:`MESSAGES`), from which the ROS 1 and ROS 2 ``.msg`` definitions
  (package ``memlog_msgs``) and the protobuf file (package ``memlog``) are generated. In ROS a
  missing number is NaN and a missing string is ``""``; in protobuf both are unset ``optional``
  fields; a missing 5x5 matrix is ``has_memorability = false`` in both.

``schemas/`` in the repository is generated from this module (``python -m memlog.outputs.schemas
schemas/``) and a test keeps the two identical. Foxglove's messages (``ImageAnnotations``,
``CompressedImage``) are not written here: their official definitions are vendored from the
``@foxglove/schemas`` npm release in ``memlog/outputs/foxglove/`` (see ``tools/foxglove_schemas.py``)
and read by :func:`foxglove_definition`.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

__all__ = [
    "SCHEMAS", "FRAME_SCORES", "MATCH", "schema_bytes",
    "Field", "Message", "MESSAGES", "ros_definition", "ros_file", "proto_file", "proto_descriptor_set",
    "foxglove_definition", "FOXGLOVE_DIR", "generated_files",
]

FOXGLOVE_DIR = Path(__file__).resolve().parent / "foxglove"

_TIME = {
    "type": "object",
    "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}},
    "required": ["sec", "nsec"],
}
_NUM_OR_NULL = {"type": ["number", "null"]}

FRAME_SCORES: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "memlog.FrameScores",
    "description": "Memorable-map scores of one camera frame (MS, SS, ES as in 'Memorable Maps'; null = not computed)",
    "type": "object",
    "properties": {
        "timestamp": {**_TIME, "description": "header stamp of the frame"},
        "log_time": {"type": "integer", "description": "log time of the frame message, ns"},
        "topic": {"type": "string"},
        "frame_index": {"type": "integer", "minimum": 0, "description": "position of the message on its topic"},
        "ms": {**_NUM_OR_NULL, "description": "memorability score; when ms_exact is false, a bound (exact mode "
               "stopped the crop loop early) or the int8 surrogate's estimate (fast mode, crops_surrogate > 0)"},
        "ms_low": _NUM_OR_NULL,
        "ms_high": _NUM_OR_NULL,
        "ms_exact": {"type": "boolean", "description": "false when the crop loop stopped early and MS is only bounded"},
        "ss": {**_NUM_OR_NULL, "description": "staticity score: fraction of static pixels"},
        "es": {**_NUM_OR_NULL, "description": "entropy score: masked mean entropy / 8 bits"},
        "memorability": {
            "description": "5x5 crop memorability matrix, row-major; null entries were not scored",
            "type": ["array", "null"],
            "items": {"type": "array", "items": _NUM_OR_NULL},
        },
        "crops_scored": {"type": "integer", "minimum": 0, "description": "crops run through the exact (fp32) model"},
        "crops_surrogate": {"type": "integer", "minimum": 0,
                            "description": "crops run through the fast-mode int8 surrogate (0 outside fast mode)"},
        "selected": {"type": "boolean"},
        "rejected_by": {"enum": [None, "staticity", "entropy", "memorability", "undecodable", "unscored"],
                        "description": "first criterion of the paper rule (MT/ST/ET) the frame fails; 'unscored': "
                                       "the staged selection of `memlog map` did not need MS and its bounds do not "
                                       "decide MT"},
        "thresholds": {
            "type": "object",
            "properties": {"mt": {"type": "number"}, "st": {"type": "number"}, "et": {"type": "number"}},
            "required": ["mt", "st", "et"],
        },
        "detections": {"type": "integer", "minimum": 0, "description": "dynamic-object boxes kept"},
        "timing_ms": {
            "type": "object",
            "description": "milliseconds per stage",
            "additionalProperties": {"type": "number"},
        },
        "error": {"type": ["string", "null"]},
        "shared": {"type": "boolean", "description": "the scores are those of an earlier pixel-identical frame "
                   "of the topic (a robot standing still): it was not scored again"},
        "shared_from": {"type": "integer", "minimum": 0,
                        "description": "frame index whose scores this record carries (its own when not shared)"},
    },
    "required": ["timestamp", "log_time", "frame_index", "ms", "ss", "es", "selected", "rejected_by", "thresholds"],
}

MATCH: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "memlog.Match",
    "description": "Best reference frames of the memorable map for one query frame",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_index": {"type": "integer"},
        "matches": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "topic": {"type": "string"},
                    "frame_index": {"type": "integer"},
                    "similarity": {"type": "number"},
                },
            },
        },
        "confidence": {"type": "number", "description": "the sequence margin (best place's sequence score minus "
                       "the next place's) when matched as a sequence, else the similarity of the best match"},
        "matched_by": {"type": "string", "description": "sequence, causal sequence or single frame"},
        "sequence_score": {"type": ["number", "null"], "description": "sequence score of the best place (mean "
                           "contrast-normalised similarity along its path, times the square root of the pairs); "
                           "null for a single frame"},
        "speed": {"type": ["number", "null"], "description": "relative speed of the best path (map coordinate per "
                  "query coordinate); null for a single frame"},
    },
    "required": ["timestamp", "frame_index", "matches", "confidence"],
}

#: JSON Schemas of memlog's own channels (Foxglove's: :func:`foxglove_definition`).
SCHEMAS: dict[str, dict[str, Any]] = {
    "memlog.FrameScores": FRAME_SCORES,
    "memlog.Match": MATCH,
}


def schema_bytes(name: str) -> bytes:
    """A JSON Schema as written into MCAP schema records: memlog's (``schemas/<name>.json``) or
    Foxglove's official one (``foxglove.ImageAnnotations``, ``foxglove.CompressedImage``)."""
    if name.startswith("foxglove."):
        return foxglove_definition(name, "jsonschema")
    return (json.dumps(SCHEMAS[name], indent=2, sort_keys=True) + "\n").encode()


# -- memlog's messages for ROS 1, ROS 2 and protobuf ---------------------------------------------

#: Field types: ROS primitive names, "time" (ROS 1 ``time`` / ROS 2 ``builtin_interfaces/Time`` /
#: ``google.protobuf.Timestamp``) or the name of another message in :data:`MESSAGES`.
_PRIMITIVES = {"bool", "uint32", "uint64", "float64", "string"}


@dataclass(frozen=True)
class Field:
    """One field of a memlog message. ``nullable``: the record's value may be null, written as NaN
    (float64) or "" (string) in ROS and as an unset proto3 ``optional`` field in protobuf."""

    name: str
    type: str
    doc: str
    array: bool = False
    nullable: bool = False


@dataclass(frozen=True)
class Message:
    name: str
    doc: str
    fields: tuple[Field, ...]

    def deps(self) -> list["Message"]:
        """Messages this one uses, depth first, each once."""
        out: list[Message] = []
        for f in self.fields:
            if f.type in MESSAGES:
                for m in [MESSAGES[f.type], *MESSAGES[f.type].deps()]:
                    if m not in out:
                        out.append(m)
        return out


MESSAGES: dict[str, Message] = {m.name: m for m in (
    Message("Thresholds", "Thresholds a frame was decided with", (
        Field("mt", "float64", "memorability threshold"),
        Field("st", "float64", "staticity threshold"),
        Field("et", "float64", "entropy threshold"),
    )),
    Message("StageTime", "Time one scoring stage took", (
        Field("stage", "string", "decode, resize, staticity, entropy or memorability"),
        Field("ms", "float64", "milliseconds"),
    )),
    Message("FrameScores", "Memorable-map scores of one camera frame (MS, SS, ES as in 'Memorable Maps').\n"
            "A value not computed (null in JSON) is NaN (numbers) or \"\" (strings) in ROS, unset in protobuf.", (
        Field("timestamp", "time", "header stamp of the frame"),
        Field("log_time", "uint64", "log time of the frame message, ns"),
        Field("topic", "string", "camera topic"),
        Field("frame_index", "uint64", "position of the message on its topic"),
        Field("ms", "float64", "memorability score; when ms_exact is false, a bound (exact mode stopped the crop "
              "loop early) or the int8 surrogate's estimate (fast mode)", nullable=True),
        Field("ms_low", "float64", "lower bound of MS", nullable=True),
        Field("ms_high", "float64", "upper bound of MS", nullable=True),
        Field("ms_exact", "bool", "false when the crop loop stopped early and MS is only bounded"),
        Field("ss", "float64", "staticity score: fraction of static pixels", nullable=True),
        Field("es", "float64", "entropy score: masked mean entropy / 8 bits", nullable=True),
        Field("has_memorability", "bool", "false when no crop matrix was computed"),
        Field("memorability_rows", "uint32", "rows of the crop matrix (5; 0 without one)"),
        Field("memorability", "float64", "crop memorability matrix, row-major; NaN = crop not scored", array=True),
        Field("crops_scored", "uint32", "crops run through the exact (fp32) model"),
        Field("crops_surrogate", "uint32", "crops run through the fast-mode int8 surrogate (0 outside fast mode)"),
        Field("selected", "bool", "the frame passes every threshold"),
        Field("rejected_by", "string", "staticity, entropy, memorability or undecodable; none when selected",
              nullable=True),
        Field("thresholds", "Thresholds", "thresholds the frame was decided with"),
        Field("detections", "uint32", "dynamic-object boxes kept"),
        Field("timing_ms", "StageTime", "milliseconds per stage, in stage order", array=True),
        Field("error", "string", "why the frame could not be scored; none when it was", nullable=True),
        Field("shared", "bool", "the scores are those of an earlier pixel-identical frame of the topic (not "
              "scored again)"),
        Field("shared_from", "uint64", "frame index whose scores this record carries (its own when not shared)"),
    )),
    Message("MatchCandidate", "A map frame matched to a query frame", (
        Field("topic", "string", "camera topic of the map frame"),
        Field("frame_index", "uint64", "position of the map frame on its topic"),
        Field("similarity", "float64", "descriptor similarity (cosine)"),
    )),
    Message("Match", "Best reference frames of the memorable map for one query frame", (
        Field("timestamp", "time", "header stamp of the query frame"),
        Field("frame_index", "uint64", "position of the query frame on its topic"),
        Field("matches", "MatchCandidate", "best map frames, best first", array=True),
        Field("confidence", "float64", "the sequence margin (best place's sequence score minus the next place's) "
              "when matched as a sequence, else the similarity of the best match"),
        Field("matched_by", "string", "sequence, causal sequence or single frame"),
        Field("sequence_score", "float64", "sequence score of the best place", nullable=True),
        Field("speed", "float64", "relative speed of the best path (map coordinate per query coordinate)",
              nullable=True),
    )),
)}


def _comment(text: str, prefix: str) -> list[str]:
    return [f"{prefix} {line}".rstrip() for line in text.split("\n")]


def ros_file(name: str, ros_version: int) -> str:
    """The ``.msg`` file of one memlog message (dependencies referenced, not merged)."""
    m = MESSAGES[name]
    lines = [f"# memlog_msgs/{'msg/' if ros_version == 2 else ''}{m.name}", *_comment(m.doc, "#"),
             "# Generated by python -m memlog.outputs.schemas", ""]
    for f in m.fields:
        if f.type == "time":
            typ = "time" if ros_version == 1 else "builtin_interfaces/Time"
        elif f.type in MESSAGES:
            typ = f"memlog_msgs/{f.type}"
        else:
            typ = f.type
        doc = f.doc + ((" (NaN: not computed)" if f.type == "float64" else ' ("": none)') if f.nullable else "")
        lines += [*_comment(doc, "#"), f"{typ}{'[]' if f.array else ''} {f.name}", ""]
    return "\n".join(lines)


def ros_definition(name: str, ros_version: int) -> str:
    """The full definition of a memlog message as an MCAP ``ros1msg``/``ros2msg`` schema (and a ROS 1
    bag's ``message_definition``): the message, then each dependency after a line of ``=``."""
    out = ros_file(name, ros_version)
    for dep in MESSAGES[name].deps():
        out += "=" * 80 + f"\nMSG: memlog_msgs/{dep.name}\n" + ros_file(dep.name, ros_version)
    return out


_PROTO_TYPES = {"bool": "bool", "uint32": "uint32", "uint64": "uint64", "float64": "double", "string": "string",
                "time": "google.protobuf.Timestamp"}


def _proto_type(f: Field) -> str:
    return f"memlog.{f.type}" if f.type in MESSAGES else _PROTO_TYPES[f.type]


def proto_file(name: str) -> str:
    """``memlog/NAME.proto``: the message and its dependencies, package ``memlog``."""
    m = MESSAGES[name]
    lines = ["// Generated by python -m memlog.outputs.schemas", "", 'syntax = "proto3";', "",
             'import "google/protobuf/timestamp.proto";', "", "package memlog;"]
    for msg in [m, *m.deps()]:
        lines += ["", *_comment(msg.doc, "//"), f"message {msg.name} {{"]
        for i, f in enumerate(msg.fields, 1):
            label = "repeated " if f.array else "optional " if f.nullable else ""
            doc = f.doc + (" (unset: none)" if f.nullable else "")
            lines += [*_comment(doc, "  //"), f"  {label}{_proto_type(f)} {f.name} = {i};"]
        lines.append("}")
    return "\n".join(lines) + "\n"


def _json_name(name: str) -> str:
    head, *rest = name.split("_")
    return head + "".join(p[:1].upper() + p[1:] for p in rest)


def proto_descriptor_set(name: str) -> bytes:
    """The FileDescriptorSet of :func:`proto_file` (what ``protoc --include_imports`` makes of it),
    built without protoc: the data of an MCAP ``protobuf`` schema record."""
    return _descriptor_set(name)


@lru_cache(maxsize=None)
def _descriptor_set(name: str) -> bytes:
    from google.protobuf import descriptor_pb2, timestamp_pb2

    F = descriptor_pb2.FieldDescriptorProto
    scalar = {"bool": F.TYPE_BOOL, "uint32": F.TYPE_UINT32, "uint64": F.TYPE_UINT64, "float64": F.TYPE_DOUBLE,
              "string": F.TYPE_STRING}
    m = MESSAGES[name]
    fd = descriptor_pb2.FileDescriptorProto(name=f"memlog/{name}.proto", package="memlog", syntax="proto3",
                                            dependency=["google/protobuf/timestamp.proto"])
    for msg in [m, *m.deps()]:
        mp = fd.message_type.add(name=msg.name)
        for i, f in enumerate(msg.fields, 1):
            fp = mp.field.add(name=f.name, number=i, json_name=_json_name(f.name),
                              label=F.LABEL_REPEATED if f.array else F.LABEL_OPTIONAL)
            if f.type in scalar:
                fp.type = scalar[f.type]
            else:
                fp.type = F.TYPE_MESSAGE
                fp.type_name = ".google.protobuf.Timestamp" if f.type == "time" else f".memlog.{f.type}"
        for f in msg.fields:  # proto3 optional: a synthetic oneof per field, after the real ones
            if f.nullable:
                fp = next(x for x in mp.field if x.name == f.name)
                fp.proto3_optional = True
                fp.oneof_index = len(mp.oneof_decl)
                mp.oneof_decl.add(name=f"_{f.name}")
    ts = descriptor_pb2.FileDescriptorProto()
    timestamp_pb2.DESCRIPTOR.CopyToProto(ts)
    return bytes(descriptor_pb2.FileDescriptorSet(file=[ts, fd]).SerializeToString())


# -- Foxglove's messages, vendored --------------------------------------------------------------

_FOXGLOVE_PATHS = {
    "jsonschema": "jsonschema/foxglove.{name}.json",
    "ros1msg": "ros1msg/foxglove_msgs/{name}.msg",
    "ros2msg": "ros2msg/foxglove_msgs/msg/{name}.msg",
    "protobuf": "fds/foxglove.{name}.fds",
}


def foxglove_definition(name: str, encoding: str) -> bytes:
    """Foxglove's official definition of ``foxglove.NAME`` as an MCAP schema record holds it for
    ``encoding`` (jsonschema, ros1msg, ros2msg or protobuf), from ``memlog/outputs/foxglove/``."""
    return _foxglove_file(name.removeprefix("foxglove."), encoding)


@lru_cache(maxsize=None)
def _foxglove_file(short: str, encoding: str) -> bytes:
    return (FOXGLOVE_DIR / _FOXGLOVE_PATHS[encoding].format(name=short)).read_bytes()


# -- schemas/ ------------------------------------------------------------------------------------

def generated_files() -> dict[str, bytes]:
    """Every file of ``schemas/`` (relative path -> bytes)."""
    out = {f"{name}.json": schema_bytes(name) for name in SCHEMAS}
    for name in MESSAGES:
        out[f"ros1/memlog_msgs/msg/{name}.msg"] = ros_file(name, 1).encode()
        out[f"ros2/memlog_msgs/msg/{name}.msg"] = ros_file(name, 2).encode()
    for name in ("FrameScores", "Match"):
        out[f"proto/memlog/{name}.proto"] = proto_file(name).encode()
    return out


def main(argv: list[str]) -> int:
    out = Path(argv[0] if argv else "schemas")
    for rel, data in generated_files().items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_bytes(data)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
