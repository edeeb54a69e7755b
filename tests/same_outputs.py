"""memlog's outputs read back without their timing fields (the only fields allowed to differ
between a one-process run and a run on workers), and what ``memlog batch`` must reproduce: the
local one-process ``score`` and ``make_map`` of a log."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from memlog.io.identity import log_name
from memlog.outputs.map_artefact import check_map_pair
from memlog.steps.batch import BatchConfig
from memlog.steps.map import make_map
from memlog.steps.score import score
from tests.stand_in import stand_in_scorer


def reference(log: Path | str, outdir: Path, cfg: BatchConfig, *, stand_in: bool) -> dict[str, Path]:
    """``memlog score`` then ``memlog map`` of ``log`` on this process, outputs named as batch names them."""
    name = log_name(log)
    outs = {"scored": outdir / f"{name}.scored.mcap", "map": outdir / f"{name}.map.mcap",
            "descriptors": outdir / f"{name}.map.parquet"}
    scorer = stand_in_scorer(cfg.map.score) if stand_in else None
    score(log, outs["scored"], cfg.map.score, cfg.window(), scorer=scorer)
    make_map(log, outs["map"], cfg.map)
    return outs


def normalised_map(path: Path) -> tuple[list[tuple[Any, ...]], dict[str, list[dict[str, Any]]], dict[str, Any]]:
    """An MCAP memlog wrote: every message but the score records (topic, times, sequence, bytes);
    the score records (decoded, whatever their encoding) without ``timing_ms``; the metadata."""
    from memlog.outputs.annotated import read_scores

    msgs = []
    with open(path, "rb") as fh:
        r = make_reader(fh, validate_crcs=True)
        for _, ch, m in r.iter_messages(log_time_order=False):
            if not ch.topic.endswith("/memlog/scores"):
                msgs.append((ch.topic, m.log_time, m.publish_time, m.sequence, bytes(m.data)))
        meta: dict[str, Any] = {md.name: dict(md.metadata) for md in r.iter_metadata()}
    link = meta.get("memlog_map_descriptors")
    if link is not None:  # the table's content hash covers its extra["map"], the map's own path
        link.pop("descriptors_sha256")
    scores = read_scores(path)
    for recs in scores.values():
        for rec in recs:
            rec.pop("timing_ms")
    return msgs, scores, meta


def normalised_scored(path: Path) -> tuple[list[tuple[Any, ...]], dict[str, list[dict[str, Any]]], dict[str, Any]]:
    """An annotated log of ``memlog score`` as :func:`normalised_map` reads it, ``memlog_summary``
    without the run's timing (``seconds``, ``mean_ms_per_frame``) and output path."""
    msgs, scores, meta = normalised_map(path)
    summary = {k: json.loads(v) for k, v in meta["memlog_summary"].items()}
    summary.pop("seconds")
    summary.pop("output")
    for t in summary["topics"].values():
        t.pop("mean_ms_per_frame")
    meta["memlog_summary"] = summary
    return msgs, scores, meta


def normalised_parquet(path: Path) -> tuple[Any, dict[bytes, Any]]:
    """The descriptor table's rows and its metadata, the map's own path (which differs by
    directory) and sha256 (which the timing fields change) left out."""
    import pyarrow.parquet as pq

    t = pq.read_table(path)
    meta = dict(t.schema.metadata or {})
    meta.pop(b"memlog.map_sha256", None)
    extra = json.loads(meta.pop(b"memlog.extra"))
    extra["map"] = Path(extra["map"]).name
    meta[b"memlog.extra"] = extra
    return t.replace_schema_metadata(None).to_pylist(), meta


def assert_same_outputs(got: dict[str, str], want: dict[str, Path]) -> None:
    """The three outputs of a batch run are the reference's, timing fields aside."""
    assert normalised_scored(Path(got["scored"])) == normalised_scored(want["scored"])
    assert normalised_map(Path(got["map"])) == normalised_map(want["map"])
    assert normalised_parquet(Path(got["descriptors"])) == normalised_parquet(want["descriptors"])
    check_map_pair(got["map"], got["descriptors"])  # (what the normalising leaves out is the pair's own)
