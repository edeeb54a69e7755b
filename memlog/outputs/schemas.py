"""JSON Schemas of every channel memlog writes.

The dicts here are the source; ``schemas/*.json`` in the repository are generated from them
(``python -m memlog.outputs.schemas schemas/``) and a test keeps the two identical.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

__all__ = ["SCHEMAS", "FRAME_SCORES", "IMAGE_ANNOTATIONS", "COMPRESSED_IMAGE", "MATCH", "schema_bytes"]

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
    },
    "required": ["timestamp", "log_time", "frame_index", "ms", "ss", "es", "selected", "rejected_by", "thresholds"],
}

_COLOR = {
    "type": "object",
    "title": "foxglove.Color",
    "properties": {k: {"type": "number"} for k in ("r", "g", "b", "a")},
}
_POINT2 = {"type": "object", "title": "foxglove.Point2", "properties": {"x": {"type": "number"}, "y": {"type": "number"}}}

IMAGE_ANNOTATIONS: dict[str, Any] = {
    "title": "foxglove.ImageAnnotations",
    "description": "Array of annotations for a 2D image",
    "$comment": "Follows the Foxglove schema (https://docs.foxglove.dev/docs/visualization/message-schemas/image-annotations)",
    "type": "object",
    "properties": {
        "circles": {"type": "array", "items": {"type": "object", "title": "foxglove.CircleAnnotation"}},
        "points": {
            "type": "array",
            "items": {
                "type": "object",
                "title": "foxglove.PointsAnnotation",
                "properties": {
                    "timestamp": _TIME,
                    "type": {"type": "integer", "description": "0 UNKNOWN, 1 POINTS, 2 LINE_LOOP, 3 LINE_STRIP, 4 LINE_LIST"},
                    "points": {"type": "array", "items": _POINT2},
                    "outline_color": _COLOR,
                    "outline_colors": {"type": "array", "items": _COLOR},
                    "fill_color": _COLOR,
                    "thickness": {"type": "number"},
                },
            },
        },
        "texts": {
            "type": "array",
            "items": {
                "type": "object",
                "title": "foxglove.TextAnnotation",
                "properties": {
                    "timestamp": _TIME,
                    "position": _POINT2,
                    "text": {"type": "string"},
                    "font_size": {"type": "number"},
                    "text_color": _COLOR,
                    "background_color": _COLOR,
                },
            },
        },
    },
}

COMPRESSED_IMAGE: dict[str, Any] = {
    "title": "foxglove.CompressedImage",
    "description": "A compressed image",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    },
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
        "confidence": {"type": "number"},
    },
    "required": ["timestamp", "frame_index", "matches", "confidence"],
}

SCHEMAS: dict[str, dict[str, Any]] = {
    "memlog.FrameScores": FRAME_SCORES,
    "foxglove.ImageAnnotations": IMAGE_ANNOTATIONS,
    "foxglove.CompressedImage": COMPRESSED_IMAGE,
    "memlog.Match": MATCH,
}


def schema_bytes(name: str) -> bytes:
    """The schema as written into MCAP schema records and ``schemas/<name>.json``."""
    return (json.dumps(SCHEMAS[name], indent=2, sort_keys=True) + "\n").encode()


def main(argv: list[str]) -> int:
    out = Path(argv[0] if argv else "schemas")
    out.mkdir(parents=True, exist_ok=True)
    for name in SCHEMAS:
        (out / f"{name}.json").write_bytes(schema_bytes(name))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
