"""Descriptor tables (:class:`~memlog.descriptors.table.DescriptorTable`) as Parquet files.

One row per frame: ``topic`` (string), ``frame_index``, ``log_time_ns``, ``stamp_ns``
(int64), the memorability scores ``ms``/``ss``/``es`` (float64, null when not scored),
``descriptor`` (``fixed_size_list<float32>[dim]``) and optional positions, either
geographic ``lat``/``lon``/``alt`` or local ``x``/``y``/``z`` (float64, nullable). In numpy
a null float is NaN (both directions).

The schema metadata records what made the descriptors (``memlog.kind``, ``memlog.version``,
``memlog.dim``, ``memlog.model_sha256``, ``memlog.params`` (JSON), ``memlog.memlog_version``)
and ``memlog.extra``: a JSON object of whatever the caller adds (source log, thresholds ...).
Whitened descriptors add ``memlog.whitening_sha256`` (the transform's sha256) and, for a map,
``memlog.whitening``: the transform itself (JSON, arrays base64; checked against its sha256 on
reading, see :mod:`memlog.descriptors.whitening`).
Files are written atomically (temporary file in the same directory, then ``os.replace``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.parquet as pq

from memlog._version import __version__
from memlog.descriptors.base import DescriptorMeta
from memlog.descriptors.table import POSITION_COLUMNS, SCORE_COLUMNS, DescriptorTable
from memlog.descriptors.whitening import Whitening
from memlog.errors import DescriptorError
from memlog.io.atomic import atomic_output

__all__ = ["write_descriptors", "read_descriptors"]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


def _meta_to_schema(meta: DescriptorMeta, extra: Mapping[str, Any], memlog_version: str,
                    whitening: Whitening | None = None) -> dict[bytes, bytes]:
    def enc(value: Any) -> bytes:
        return json.dumps(value, sort_keys=True).encode()

    white: dict[bytes, bytes] = {}
    if meta.whitening:
        white[b"memlog.whitening_sha256"] = meta.whitening.encode()
    if whitening is not None:
        white[b"memlog.whitening"] = whitening.to_json().encode()
    try:
        return {
            **white,
            b"memlog.kind": meta.kind.encode(),
            b"memlog.version": meta.version.encode(),
            b"memlog.dim": str(meta.dim).encode(),
            b"memlog.model_sha256": (meta.model_sha256 or "").encode(),
            b"memlog.params": enc(meta.params),
            b"memlog.memlog_version": memlog_version.encode(),
            b"memlog.extra": enc(dict(extra)),
        }
    except (TypeError, ValueError) as exc:
        raise DescriptorError(f"descriptor metadata is not JSON-serialisable: {exc}") from None


def write_descriptors(path: str | os.PathLike[str], table: DescriptorTable) -> Path:
    """Write ``table`` to the Parquet file ``path`` atomically; return the path."""
    n, dim = table.descriptors.shape
    flat = pa.array(table.descriptors.reshape(-1), type=pa.float32())
    arrays: dict[str, pa.Array] = {
        "topic": pa.array(table.topic, type=pa.string()),
        "frame_index": pa.array(table.frame_index, type=pa.int64()),
        "log_time_ns": pa.array(table.log_time_ns, type=pa.int64()),
        "stamp_ns": pa.array(table.stamp_ns, type=pa.int64()),
    }
    for name in SCORE_COLUMNS:
        arrays[name] = pa.array(getattr(table, name), type=pa.float64(), from_pandas=True)
    arrays["descriptor"] = pa.FixedSizeListArray.from_arrays(flat, dim)
    for cols in POSITION_COLUMNS.values():
        for name in cols:
            if name in table.positions:
                arrays[name] = pa.array(table.positions[name], type=pa.float64(), from_pandas=True)
    schema_meta = _meta_to_schema(table.meta, table.extra, table.memlog_version or __version__, table.whitening)
    pa_table = pa.table(arrays).replace_schema_metadata(schema_meta)
    target = Path(path)
    try:
        with atomic_output(target) as tmp:
            pq.write_table(pa_table, tmp, compression="zstd")
    except OSError as exc:
        raise DescriptorError(f"could not write {target}: {exc}") from None
    return target


def _meta_from_schema(
    md: Mapping[bytes, bytes] | None, path: Path
) -> tuple[DescriptorMeta, dict[str, Any], str, Whitening | None]:
    if not md or b"memlog.kind" not in md:
        raise DescriptorError(f"{path} is not a memlog descriptor table (no memlog schema metadata)")
    try:
        sha = md.get(b"memlog.model_sha256", b"").decode()
        meta = DescriptorMeta(
            kind=md[b"memlog.kind"].decode(),
            version=md[b"memlog.version"].decode(),
            dim=int(md[b"memlog.dim"]),
            model_sha256=sha or None,
            params=json.loads(md.get(b"memlog.params", b"{}")),
            whitening=md.get(b"memlog.whitening_sha256", b"").decode() or None,
        )
        extra = json.loads(md.get(b"memlog.extra", b"{}"))
        version = md.get(b"memlog.memlog_version", b"").decode()
        white_json = md.get(b"memlog.whitening")
        white = None if white_json is None else json.loads(white_json)
    except (KeyError, ValueError, UnicodeDecodeError) as exc:
        raise DescriptorError(f"{path} has invalid memlog metadata: {exc}") from None
    whitening = None
    if white is not None:
        try:
            whitening = Whitening.from_dict(white)
        except DescriptorError as exc:
            raise DescriptorError(f"{path}: {exc}") from None
        if whitening.sha256 != meta.whitening:
            raise DescriptorError(f"{path}: the stored whitening transform (sha256 {whitening.sha256[:12]}…) is not "
                                  f"the one the descriptors name ({str(meta.whitening)[:12]}…)")
    return meta, extra, version, whitening


def read_descriptors(path: str | os.PathLike[str]) -> DescriptorTable:
    """Read a table written by :func:`write_descriptors` (DescriptorError if it is not one)."""
    p = Path(path)
    try:
        table = pq.read_table(p)
    except (OSError, pa.ArrowException) as exc:
        raise DescriptorError(f"could not read descriptor table {p}: {exc}") from None
    meta, extra, version, whitening = _meta_from_schema(table.schema.metadata, p)
    required = ("topic", "frame_index", "log_time_ns", "stamp_ns", "descriptor")
    missing = [c for c in required if c not in table.column_names]
    if missing:
        raise DescriptorError(f"{p} lacks column(s) {', '.join(missing)}")
    desc_col = table.column("descriptor").combine_chunks()
    if not pa.types.is_fixed_size_list(desc_col.type) or desc_col.type.list_size != meta.dim:
        raise DescriptorError(f"{p}: descriptor column type {desc_col.type} does not match dim {meta.dim}")
    if desc_col.null_count:
        raise DescriptorError(f"{p}: {desc_col.null_count} descriptor(s) are null")
    desc = desc_col.flatten().to_numpy(zero_copy_only=False).astype(np.float32).reshape(-1, meta.dim)

    def floats(name: str) -> F64:
        arr: F64 = table.column(name).to_numpy().astype(np.float64)  # nulls become NaN
        return arr

    def ints(name: str) -> I64:
        col = table.column(name)
        if col.null_count:
            raise DescriptorError(f"{p}: column {name} has nulls")
        arr: I64 = col.to_numpy().astype(np.int64)
        return arr

    positions = {c: floats(c) for cols in POSITION_COLUMNS.values() for c in cols if c in table.column_names}
    return DescriptorTable(
        topic=[str(t) for t in table.column("topic").to_pylist()],
        frame_index=ints("frame_index"),
        log_time_ns=ints("log_time_ns"),
        stamp_ns=ints("stamp_ns"),
        descriptors=desc,
        meta=meta,
        ms=floats("ms") if "ms" in table.column_names else None,
        ss=floats("ss") if "ss" in table.column_names else None,
        es=floats("es") if "es" in table.column_names else None,
        positions=positions,
        extra=extra,
        memlog_version=version or None,
        whitening=whitening,
    )
