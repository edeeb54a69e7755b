"""What the ROS 1 and ROS 2 bag readers share with rosbags: the message definition of a connection."""

from __future__ import annotations

from typing import Any

__all__ = ["msgdef_text"]


def msgdef_text(conn: Any) -> tuple[str, str]:
    """(definition text, format: "msg" or "idl") of a rosbags connection."""
    md = getattr(conn, "msgdef", None)
    if md is None:
        return "", "msg"
    data = getattr(md, "data", md)
    fmt = getattr(getattr(md, "format", None), "name", "MSG")
    return (data if isinstance(data, str) else str(data)), fmt.lower()
