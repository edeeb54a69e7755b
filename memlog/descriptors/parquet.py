"""Reference descriptor tables in Parquet: write, read, and refuse incompatible pairs.

One row per frame: ``topic`` (string), ``frame_index``, ``log_time_ns``, ``stamp_ns``
(int64), the memorability scores ``ms``/``ss``/``es`` (float64, null when not scored),
``descriptor`` (``fixed_size_list<float32>[dim]``) and optional positions, either
geographic ``lat``/``lon``/``alt`` or local ``x``/``y``/``z`` (float64, nullable). In numpy
a null float is NaN (both directions).

The schema metadata records what made the descriptors (``memlog.kind``, ``memlog.version``,
``memlog.dim``, ``memlog.model_sha256``, ``memlog.params`` (JSON), ``memlog.memlog_version``)
and ``memlog.extra``: a JSON object of whatever the caller adds (source log, thresholds ...).
Files are written atomically (temporary file in the same directory, then ``os.replace``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.parquet as pq

from memlog.descriptors.base import DescriptorMeta
from memlog.io.atomic import atomic_output
from memlog.errors import DescriptorError

__all__ = [
    "DescriptorTable",
    "write_descriptors",
    "read_descriptors",
    "check_compatible",
    "atomic_output",
    "POSITION_COLUMNS",
]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Allowed position column sets: geographic (degrees, metres) or local (metres).
POSITION_COLUMNS: dict[str, tuple[str, ...]] = {"geo": ("lat", "lon", "alt"), "local": ("x", "y", "z")}
_SCORES = ("ms", "ss", "es")
_PREFIX = "memlog."


@dataclass
class DescriptorTable:
    """Descriptors of ``N`` frames with their identities, scores, positions and metadata.

    ``descriptors`` is ``[N, dim]`` float32; ``ms``/``ss``/``es`` are float64 with NaN for
    "not scored"; ``positions`` maps column names of one :data:`POSITION_COLUMNS` set to
    float64 arrays (NaN = unknown). ``extra`` is caller metadata stored as JSON.
    """

    topic: list[str]
    frame_index: I64
    log_time_ns: I64
    stamp_ns: I64
    descriptors: npt.NDArray[np.float32]
    meta: DescriptorMeta
    ms: F64 | None = None
    ss: F64 | None = None
    es: F64 | None = None
    positions: dict[str, F64] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)
    memlog_version: str | None = None

    def __post_init__(self) -> None:
        self.descriptors = np.ascontiguousarray(self.descriptors, dtype=np.float32)
        if self.descriptors.ndim != 2:
            raise DescriptorError(f"descriptors must be [N, dim], got shape {self.descriptors.shape}")
        n, dim = self.descriptors.shape
        if dim != self.meta.dim:
            raise DescriptorError(f"descriptors have dim {dim} but the metadata says {self.meta.dim}")
        self.topic = [str(t) for t in self.topic]
        self.frame_index = np.asarray(self.frame_index, dtype=np.int64)
        self.log_time_ns = np.asarray(self.log_time_ns, dtype=np.int64)
        self.stamp_ns = np.asarray(self.stamp_ns, dtype=np.int64)
        for name in _SCORES:
            val = getattr(self, name)
            setattr(self, name, np.full(n, np.nan) if val is None else np.asarray(val, dtype=np.float64))
        self.positions = {k: np.asarray(v, dtype=np.float64) for k, v in self.positions.items()}
        used = [kind for kind, cols in POSITION_COLUMNS.items() if set(self.positions) & set(cols)]
        unknown = set(self.positions) - {c for cols in POSITION_COLUMNS.values() for c in cols}
        if unknown or len(used) > 1:
            raise DescriptorError(
                f"positions must use columns of one set {POSITION_COLUMNS}, got {sorted(self.positions)}"
            )
        columns: dict[str, Any] = {
            "topic": self.topic,
            "frame_index": self.frame_index,
            "log_time_ns": self.log_time_ns,
            "stamp_ns": self.stamp_ns,
            **{s: getattr(self, s) for s in _SCORES},
            **self.positions,
        }
        for name, col in columns.items():
            if len(col) != n or (isinstance(col, np.ndarray) and col.ndim != 1):
                raise DescriptorError(f"column {name} has {len(col)} values for {n} descriptors")

    def __len__(self) -> int:
        return int(self.descriptors.shape[0])


def _meta_to_schema(meta: DescriptorMeta, extra: Mapping[str, Any], memlog_version: str) -> dict[bytes, bytes]:
    def enc(value: Any) -> bytes:
        return json.dumps(value, sort_keys=True).encode()

    try:
        return {
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
    from memlog import __version__

    n, dim = table.descriptors.shape
    flat = pa.array(table.descriptors.reshape(-1), type=pa.float32())
    arrays: dict[str, pa.Array] = {
        "topic": pa.array(table.topic, type=pa.string()),
        "frame_index": pa.array(table.frame_index, type=pa.int64()),
        "log_time_ns": pa.array(table.log_time_ns, type=pa.int64()),
        "stamp_ns": pa.array(table.stamp_ns, type=pa.int64()),
    }
    for name in _SCORES:
        arrays[name] = pa.array(getattr(table, name), type=pa.float64(), from_pandas=True)
    arrays["descriptor"] = pa.FixedSizeListArray.from_arrays(flat, dim)
    for cols in POSITION_COLUMNS.values():
        for name in cols:
            if name in table.positions:
                arrays[name] = pa.array(table.positions[name], type=pa.float64(), from_pandas=True)
    schema_meta = _meta_to_schema(table.meta, table.extra, table.memlog_version or __version__)
    pa_table = pa.table(arrays).replace_schema_metadata(schema_meta)
    target = Path(path)
    try:
        with atomic_output(target) as tmp:
            pq.write_table(pa_table, tmp, compression="zstd")
    except OSError as exc:
        raise DescriptorError(f"could not write {target}: {exc}") from None
    return target


def _meta_from_schema(md: Mapping[bytes, bytes] | None, path: Path) -> tuple[DescriptorMeta, dict[str, Any], str]:
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
        )
        extra = json.loads(md.get(b"memlog.extra", b"{}"))
        version = md.get(b"memlog.memlog_version", b"").decode()
    except (KeyError, ValueError, UnicodeDecodeError) as exc:
        raise DescriptorError(f"{path} has invalid memlog metadata: {exc}") from None
    return meta, extra, version


def read_descriptors(path: str | os.PathLike[str]) -> DescriptorTable:
    """Read a table written by :func:`write_descriptors` (DescriptorError if it is not one)."""
    p = Path(path)
    try:
        table = pq.read_table(p)
    except (OSError, pa.ArrowException) as exc:
        raise DescriptorError(f"could not read descriptor table {p}: {exc}") from None
    meta, extra, version = _meta_from_schema(table.schema.metadata, p)
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
    )


def _as_meta(m: DescriptorMeta | DescriptorTable | Mapping[str, Any]) -> DescriptorMeta:
    if isinstance(m, DescriptorTable):
        return m.meta
    if isinstance(m, DescriptorMeta):
        return m
    return DescriptorMeta(
        kind=str(m["kind"]),
        version=str(m["version"]),
        dim=int(m["dim"]),
        model_sha256=m.get("model_sha256"),
        params=dict(m.get("params") or {}),
    )


def _describe(m: DescriptorMeta) -> str:
    sha = f"sha256 {m.model_sha256[:12]}…" if m.model_sha256 else "no model"
    params = ", ".join(f"{k}={v}" for k, v in sorted(m.params.items()))
    return f"{m.kind} v{m.version} ({m.dim}-d, {sha}{'; ' + params if params else ''})"


def check_compatible(
    map_meta: DescriptorMeta | DescriptorTable | Mapping[str, Any],
    query_meta: DescriptorMeta | DescriptorTable | Mapping[str, Any],
) -> None:
    """Raise :class:`DescriptorError` unless both were made by the same describer.

    Compares kind, version, dim, model sha256 and params, e.g. "map built with dinov2-cls v1
    (384-d, sha256 198644e37de3…), query described with thumbnail v1 (2048-d, no model)".
    """
    a, b = _as_meta(map_meta), _as_meta(query_meta)
    fields = ("kind", "version", "dim", "model_sha256", "params")
    diff = [f for f in fields if getattr(a, f) != getattr(b, f)]
    if diff:
        raise DescriptorError(
            f"map built with {_describe(a)}, query described with {_describe(b)}: "
            f"{', '.join(diff)} differ; describe both with the same descriptor"
        )
