"""A ROS 2 bag's ``metadata.yaml``: read, and compared with what the storage files hold (it is
only checked, never trusted; see :mod:`memlog.io.rosbag2.reader`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from memlog.io._damage import check_regular_file

__all__ = ["read_metadata", "metadata_problems"]


def read_metadata(d: Path) -> tuple[dict[str, Any] | None, str]:
    """The ``rosbag2_bagfile_information`` of the bag directory ``d``'s metadata.yaml, or None and
    why it is not usable."""
    p = d / "metadata.yaml"
    if not p.exists():
        return None, "metadata.yaml is missing"
    try:
        check_regular_file(str(p))
        from ruamel.yaml import YAML

        with open(p, encoding="utf-8") as fh:
            doc = YAML(typ="safe", pure=True).load(fh)
        info = doc["rosbag2_bagfile_information"]
        if not isinstance(info, dict):
            raise TypeError("rosbag2_bagfile_information is not a mapping")
        return info, ""
    except Exception as exc:  # noqa: BLE001 - yaml, unicode, key and type errors all mean: not usable
        return None, f"metadata.yaml does not parse ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"


def metadata_problems(meta: dict[str, Any], files: list[Path], counts: dict[int, int] | None,
                      by_topic: dict[tuple[str, str], int], kinds: set[str]) -> list[str]:
    """How metadata.yaml (``meta``) disagrees with the storage: its ``files``, the messages per
    channel id (``counts``; None: not known), the channel id of each (topic, type) (``by_topic``)
    and the storage ``kinds`` ("sqlite3", "mcap"); empty when it agrees."""
    problems = []
    rel = meta.get("relative_file_paths")
    named = {r for r in rel if isinstance(r, str)} if isinstance(rel, list) else set()
    found = {f.name for f in files}
    if named != found:
        problems.append(f"it names the files {sorted(named)}, the bag holds {sorted(found)}")
    claimed: dict[tuple[str, str], int] = {}
    for t in meta.get("topics_with_message_count") or []:
        try:
            tm = t["topic_metadata"]
            claimed[(str(tm["name"]), str(tm["type"]))] = int(t["message_count"])
        except (KeyError, TypeError, ValueError):
            problems.append("a topic entry is malformed")
    have = {k: (counts or {}).get(g, 0) for k, g in by_topic.items()}
    if set(claimed) != set(have):
        problems.append(f"it lists the topics {sorted(claimed)}, the storage holds {sorted(have)}")
    elif counts is not None and claimed != have:
        problems.append("its message counts differ from the storage's "
                        + ", ".join(f"{k[0]} {claimed[k]} vs {have[k]}" for k in claimed if claimed[k] != have[k]))
    storage = str(meta.get("storage_identifier") or "")
    if storage not in kinds or len(kinds) > 1:
        problems.append(f"its storage is {storage!r}, the files are {' and '.join(sorted(kinds))}")
    mode = str(meta.get("compression_mode") or "").lower()
    fmt = str(meta.get("compression_format") or "").lower()
    zipped = any(f.name.endswith(".zstd") for f in files)
    if (mode == "file") != zipped or (mode not in ("", "none", "file", "message")) or (
            mode in ("file", "message") and fmt != "zstd"):
        problems.append(f"its compression ({mode or 'none'} {fmt}) does not match the files")
    return problems
