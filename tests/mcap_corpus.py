"""The official MCAP conformance corpus (``../shared/data/mcap_conformance``: 416 valid files, each
with the records a reader must yield in a ``.json`` beside it) and how memlog fares on one file:
its reader, ``memlog inspect`` and ``memlog convert`` (run in this process, as ``memlog`` runs
them), compared with the expected records. A converted file is read back by the ``mcap`` library's
own stream reader, CRCs validated, never by memlog's. Used by ``tests/test_mcap_conformance.py``
and ``benchmarks/mcap_conformance.py``."""

from __future__ import annotations

import contextlib
import io
import json
import os
from collections import Counter
from pathlib import Path
from typing import Any

from mcap.records import Attachment, Channel, Message, Metadata, Schema, Statistics
from mcap.stream_reader import StreamReader

from memlog.cli import main
from memlog.io import open_log
from memlog.io._opened import clear_cache

SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", Path(__file__).resolve().parent.parent.parent / "shared" / "data"))
CORPUS = SHARED / "mcap_conformance"
CASES = ["NoData", "OneAttachment", "OneMessage", "OneMetadata", "OneSchemalessMessage", "TenMessages"]
KINDS = ["messages", "channels", "schemas", "attachments", "metadata"]

Records = dict[str, Any]


def features(path: Path) -> str:
    """The feature suffix of a corpus file's name (``ch-chx-mx``), "plain" for none."""
    return "-".join(path.stem.split("-")[1:]) or "plain"


def _bytes(v: Any) -> Any:
    return bytes(int(b) for b in v) if isinstance(v, list) else v


def _empty() -> Records:
    return {"messages": [], "channels": {}, "schemas": {}, "attachments": [], "metadata": []}


def expected(path: Path) -> Records:
    """The records the corpus says a reader must yield for ``path``: messages as (channel id,
    sequence, log time, publish time, data) in file order, channels and schemas by id,
    attachments and metadata in file order."""
    out = _empty()
    for rec in json.loads(path.with_suffix(".json").read_text())["records"]:
        f = {k: _bytes(v) for k, v in rec["fields"]}
        kind = rec["type"]
        if kind == "Message":
            out["messages"].append((int(f["channel_id"]), int(f["sequence"]), int(f["log_time"]),
                                    int(f["publish_time"]), f["data"]))
        elif kind == "Channel":
            out["channels"][int(f["id"])] = (f["topic"], f["message_encoding"], int(f["schema_id"]), f["metadata"])
        elif kind == "Schema":
            out["schemas"][int(f["id"])] = (f["name"], f["encoding"], f["data"])
        elif kind == "Attachment":
            out["attachments"].append((f["name"], f["media_type"], int(f["log_time"]), int(f["create_time"]),
                                       f["data"]))
        elif kind == "Metadata":
            out["metadata"].append((f["name"], f["metadata"]))
    return out


def memlog_read(path: Path) -> tuple[Records, list[str]]:
    """What memlog's reader yields for ``path``, and the damage its report names (read afresh, as
    a new process would: what an earlier reader in this process learned is dropped)."""
    clear_cache()
    out = _empty()
    with open_log(path) as log:
        log.quiet_warnings()
        for m in log.messages(log_time_order=False):
            out["messages"].append((m.channel.id, m.sequence, m.log_time, m.publish_time, m.data))
        for c in log.channels():
            sid = c.schema.id if c.schema is not None else 0
            out["channels"][c.id] = (c.topic, c.message_encoding, sid, c.metadata)
            if c.schema is not None:
                out["schemas"][sid] = (c.schema.name, c.schema.encoding, c.schema.data)
        out["attachments"] = [(a.name, a.media_type, a.log_time, a.create_time, a.data) for a in log.attachments()]
        out["metadata"] = [(n, d) for n, d in log.metadata()]
        return out, log.report.damage()


def library_read(path: Path) -> tuple[Records, Statistics | None]:
    """Every record of ``path`` through the ``mcap`` library's stream reader (CRCs validated); a
    schema or channel id defined twice in two ways raises."""
    out = _empty()
    stats = None
    with open(path, "rb") as fh:
        for r in StreamReader(fh, validate_crcs=True).records:
            if isinstance(r, Message):
                out["messages"].append((r.channel_id, r.sequence, r.log_time, r.publish_time, bytes(r.data)))
            elif isinstance(r, Channel):
                c = (r.topic, r.message_encoding, r.schema_id, dict(r.metadata))
                if out["channels"].setdefault(r.id, c) != c:
                    raise ValueError(f"{path}: channel {r.id} defined twice")
            elif isinstance(r, Schema):
                s = (r.name, r.encoding, bytes(r.data))
                if out["schemas"].setdefault(r.id, s) != s:
                    raise ValueError(f"{path}: schema {r.id} defined twice")
            elif isinstance(r, Attachment):
                out["attachments"].append((r.name, r.media_type, r.log_time, r.create_time, bytes(r.data)))
            elif isinstance(r, Metadata):
                out["metadata"].append((r.name, dict(r.metadata)))
            elif isinstance(r, Statistics):
                stats = r
    return out, stats


def run_cli(*args: str) -> tuple[int, str, str]:
    """``memlog ARGS`` in this process, as a new process runs it (what an earlier reader in this
    process learned is dropped): exit code, standard output and standard error."""
    clear_cache()
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(list(args))
    return rc, out.getvalue(), err.getvalue()


def differences(got: Records, want: Records) -> list[str]:
    """The kinds of record (:data:`KINDS`) where ``got`` is not ``want``."""
    return [k for k in KINDS if got[k] != want[k]]


def check_read(path: Path) -> list[str]:
    """What memlog's reader gets wrong on ``path`` (empty: nothing)."""
    try:
        got, damage = memlog_read(path)
    except Exception as exc:  # noqa: BLE001 - a failure to report, not to stop on
        return [f"read raised {type(exc).__name__}: {exc}"]
    return differences(got, expected(path)) + [f"damage: {d}" for d in damage]


def check_inspect(path: Path) -> list[str]:
    """``memlog inspect --json``: exit 0 and a message count per topic equal to the expected."""
    rc, out, err = run_cli("inspect", "--json", "-q", str(path))
    if rc != 0:
        return [f"inspect exit {rc}: {err.strip()[-300:]}"]
    want = expected(path)
    topics = Counter(want["channels"][m[0]][0] for m in want["messages"])
    got = {t["topic"]: t["count"] for t in json.loads(out)["topics"] if t["count"]}
    return [] if got == dict(topics) else [f"inspect counts {got} != {dict(topics)}"]


def check_convert(path: Path, out: Path) -> list[str]:
    """``memlog convert PATH -o OUT``: exit 0, and OUT holds exactly the expected records (ids
    included), with statistics that count the input's channels and schemas."""
    rc, _, err = run_cli("convert", "-q", str(path), "-o", str(out))
    if rc != 0:
        return [f"convert exit {rc}: {err.strip()[-300:]}"]
    want = expected(path)
    try:
        got, stats = library_read(out)
    except Exception as exc:  # noqa: BLE001
        return [f"output: {exc}"]
    wrong = [f"output {k}" for k in differences(got, want)]
    if stats is None or (stats.channel_count, stats.schema_count) != (len(want["channels"]), len(want["schemas"])):
        wrong.append("output statistics")
    return wrong
