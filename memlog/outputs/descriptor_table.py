"""Descriptor tables (:class:`~memlog.descriptors.table.DescriptorTable`) as Parquet files.

One row per frame: ``topic`` (string), ``frame_index``, ``log_time_ns``, ``stamp_ns``
(int64), the memorability scores ``ms``/``ss``/``es`` (float64, null when not scored),
``descriptor`` (``fixed_size_list<float32 not null>[dim] not null``, or ``float16`` elements
when written with ``dtype="float16"``) and optional positions, either geographic
``lat``/``lon``/``alt`` or local ``x``/``y``/``z`` (float64, nullable), and optionally
``moving_index`` (int64: the frame index with the drive's stops left out, what sequence matching
runs along; absent in files written before it; ``memlog.extra``'s ``stops`` says how its stops
were found — rule, ``still_distance``, the motion rule's thresholds and the ``source`` that
decided: the log's motion or its images —, :func:`memlog.scoring.motion.stop_rule`, absent in
files written before it was recorded). In numpy a null float is NaN (both directions).

Storage: the descriptor column is plain-encoded (no dictionary) and zstd-compressed, in row
groups of about 16 MiB of descriptors, so a reader can stream it; the topic column is
dictionary-encoded. :func:`read_descriptors` fills one ``[N, dim]`` float32 matrix batch by
batch straight from Arrow buffers (no Python objects per row; peak memory about the matrix plus
one batch). Files written before (nullable, dictionary-encoded, one row group) read the same,
more slowly.

float16 storage (``dtype="float16"``) halves the file; the file says so in ``memlog.dtype``
(absent means float32) and is read back to float32. Values beyond float16's range are refused.

The schema metadata records what made the descriptors (``memlog.kind``, ``memlog.version``,
``memlog.dim``, ``memlog.model_sha256``, ``memlog.params`` (JSON), ``memlog.memlog_version``)
and ``memlog.extra``: a JSON object of whatever the caller adds (source log, thresholds ...).
Whitened descriptors add ``memlog.whitening_sha256`` (the transform's sha256) and, for a map,
``memlog.whitening``: the transform itself (JSON, arrays base64; checked against its sha256 on
reading, see :mod:`memlog.descriptors.whitening`). A map's table also records the map it
belongs to, ``memlog.map_sha256`` and ``memlog.map_file`` (:mod:`memlog.outputs.map_artefact`).

Patch features for re-ranking (:mod:`memlog.descriptors.patches`), when the describer gives
them: column ``patches`` (``fixed_size_list<float16>[P * d]``, plain-encoded, zstd), each row a
frame's ``P`` pooled patches of ``d`` values; ``memlog.patch_shape`` is ``[P, d]`` and
``memlog.patch_pca`` (JSON, arrays base64, checked against its sha256 on reading) the PCA that
projected them — a map's patches are projected; a cached query or reference table of
``memlog evaluate`` keeps them raw (no ``memlog.patch_pca``). Files without the column read with
``patches`` None.
Files are written atomically (temporary file in the same directory, then ``os.replace``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.parquet as pq

from memlog._version import __version__
from memlog.descriptors.base import DescriptorMeta, check_compatible
from memlog.descriptors.patches import PatchPCA
from memlog.descriptors.table import POSITION_COLUMNS, SCORE_COLUMNS, DescriptorTable
from memlog.descriptors.whitening import Whitening
from memlog.errors import DescriptorError
from memlog.io.atomic import atomic_output
from memlog.io.base import FrameWindow
from memlog.io.identity import same_identity
from memlog.progress import info
from memlog.scoring.motion import STILL_DISTANCE, stops_found_otherwise

__all__ = ["write_descriptors", "read_descriptors", "read_cached", "stored_dtype", "DTYPES", "descriptor_arrow",
           "write_arrow"]

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Storage types of the descriptor column: name -> Arrow element type.
DTYPES: dict[str, pa.DataType] = {"float32": pa.float32(), "float16": pa.float16()}
ROW_GROUP_BYTES = 1 << 24  # descriptor bytes per Parquet row group (and per read batch): 16 MiB
FLOAT16_MAX = float(np.finfo(np.float16).max)


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


def _descriptor_column(desc: npt.NDArray[np.floating[Any]], dtype: str) -> pa.FixedSizeListArray:
    """The ``[N, dim]`` matrix as a non-null fixed-size list column of ``dtype`` (no copy for float32)."""
    if dtype not in DTYPES:
        raise DescriptorError(f"descriptor dtype must be one of {', '.join(DTYPES)}, got {dtype!r}")
    n, dim = desc.shape
    if dtype == "float16":
        big = max(float(desc.max()), -float(desc.min())) if desc.size else 0.0
        if big > FLOAT16_MAX:
            raise DescriptorError(f"descriptors cannot be stored as float16: a value of magnitude {big:g} is "
                                  f"beyond float16's range ({FLOAT16_MAX:g}); store them as float32")
        desc = desc.astype(np.float16)
    flat = pa.array(desc.reshape(-1), type=DTYPES[dtype])
    return pa.FixedSizeListArray.from_arrays(flat, type=pa.list_(pa.field("element", DTYPES[dtype], nullable=False), dim))


def descriptor_arrow(table: DescriptorTable, *, dtype: str = "float32") -> pa.Table:
    """``table`` as the Arrow table :func:`write_descriptors` stores, schema metadata included
    (``dtype`` as there)."""
    fields: list[pa.Field] = []
    arrays: list[pa.Array] = []

    def add(name: str, arr: pa.Array, nullable: bool = True) -> None:
        fields.append(pa.field(name, arr.type, nullable=nullable))
        arrays.append(arr)

    add("topic", pa.array(table.topic, type=pa.string()))
    for name in ("frame_index", "log_time_ns", "stamp_ns"):
        add(name, pa.array(getattr(table, name), type=pa.int64()))
    for name in SCORE_COLUMNS:
        add(name, pa.array(getattr(table, name), type=pa.float64(), from_pandas=True))
    add("descriptor", _descriptor_column(table.descriptors, dtype), nullable=False)
    for cols in POSITION_COLUMNS.values():
        for name in cols:
            if name in table.positions:
                add(name, pa.array(table.positions[name], type=pa.float64(), from_pandas=True))
    if table.moving_index is not None:
        add("moving_index", pa.array(table.moving_index, type=pa.int64()), nullable=False)
    if table.patches is not None:
        n, p, d = table.patches.shape
        add("patches", _descriptor_column(table.patches.reshape(n, p * d), "float16"), nullable=False)
    schema_meta = _meta_to_schema(table.meta, table.extra, table.memlog_version or __version__, table.whitening)
    schema_meta[b"memlog.dtype"] = dtype.encode()
    if table.patches is not None:
        schema_meta[b"memlog.patch_shape"] = json.dumps(list(table.patches.shape[1:])).encode()
        if table.patch_pca is not None:
            schema_meta[b"memlog.patch_pca"] = table.patch_pca.to_json().encode()
    return pa.Table.from_arrays(arrays, schema=pa.schema(fields, metadata=schema_meta))


def write_arrow(where: str | os.PathLike[str] | BinaryIO, arrow: pa.Table) -> None:
    """Write a table made by :func:`descriptor_arrow` as Parquet to ``where`` (a path or an open
    binary file, which stays open), with the storage this module describes. Not atomic: give it
    a temporary file (:func:`write_descriptors` does)."""
    row_bytes = 0
    for name in ("descriptor", "patches"):
        if name in arrow.schema.names:
            typ = arrow.schema.field(name).type
            row_bytes += typ.list_size * typ.value_type.bit_width // 8
    row_bytes = max(1, row_bytes)
    pq.write_table(arrow, where, compression="zstd", use_dictionary=["topic"],  # patches: plain, like descriptor
                   row_group_size=max(1, ROW_GROUP_BYTES // row_bytes))


def write_descriptors(path: str | os.PathLike[str], table: DescriptorTable, *, dtype: str = "float32") -> Path:
    """Write ``table`` to the Parquet file ``path`` atomically; return the path.

    ``dtype`` is the storage type of the descriptors: ``"float32"`` (exact) or ``"float16"``
    (half the size; recorded in the metadata, read back to float32; DescriptorError when a
    value is beyond float16's range).
    """
    arrow = descriptor_arrow(table, dtype=dtype)
    target = Path(path)
    try:
        with atomic_output(target) as tmp:
            write_arrow(tmp, arrow)
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


def stored_dtype(path: str | os.PathLike[str]) -> str:
    """How the descriptors of the table at ``path`` are stored: ``"float32"`` or ``"float16"``.

    Reads only the file's footer; DescriptorError if it is not a descriptor table or if the
    metadata and the column disagree.
    """
    p = Path(path)
    try:
        schema = pq.read_schema(p)
    except (OSError, pa.ArrowException) as exc:
        raise DescriptorError(f"could not read descriptor table {p}: {exc}") from None
    meta, _extra, _version, _white = _meta_from_schema(schema.metadata, p)
    return _check_descriptor_field(schema, meta.dim, p)


def _check_descriptor_field(schema: pa.Schema, dim: int, path: Path) -> str:
    """The storage dtype of the descriptor column, checked against the metadata's dim and dtype."""
    if "descriptor" not in schema.names:
        raise DescriptorError(f"{path} lacks column(s) descriptor")
    typ = schema.field("descriptor").type
    if not pa.types.is_fixed_size_list(typ) or typ.list_size != dim:
        raise DescriptorError(f"{path}: descriptor column type {typ} does not match dim {dim}")
    stored = next((name for name, t in DTYPES.items() if typ.value_type == t), None)
    if stored is None:
        raise DescriptorError(f"{path}: descriptor elements are {typ.value_type}; expected float32 or float16")
    md = schema.metadata or {}
    said = md.get(b"memlog.dtype", b"float32").decode(errors="replace")
    if said != stored:
        raise DescriptorError(f"{path}: the metadata says the descriptors are {said} but the column holds {stored}")
    return stored


def _read_matrix(pf: pq.ParquetFile, n: int, dim: int, path: Path, column: str = "descriptor",
                 dtype: type[np.floating[Any]] = np.float32) -> npt.NDArray[Any]:
    """A fixed-size-list ``column`` as one ``[n, dim]`` matrix of ``dtype``, filled batch by batch."""
    out = np.empty((n, dim), dtype=dtype)
    rows = max(1, ROW_GROUP_BYTES // (np.dtype(dtype).itemsize * max(1, dim)))
    start = 0
    # one thread, no pre-buffering: Arrow then holds about one row group (measured fastest here too)
    for batch in pf.iter_batches(batch_size=rows, columns=[column], use_threads=False):
        col = batch.column(0)
        if col.null_count:
            raise DescriptorError(f"{path}: {col.null_count} {column}(s) are null")
        values = col.flatten()  # honours the slice offset; no copy
        if values.null_count:
            raise DescriptorError(f"{path}: {column} holds {values.null_count} null value(s)")
        m = len(col)
        if start + m > n:
            raise DescriptorError(f"{path}: more {column} rows than the file's {n} rows")
        out[start : start + m] = values.to_numpy(zero_copy_only=True).reshape(m, dim)
        start += m
    if start != n:
        raise DescriptorError(f"{path}: read {start} {column} rows of {n}")
    return out


def read_descriptors(path: str | os.PathLike[str]) -> DescriptorTable:
    """Read a table written by :func:`write_descriptors` (DescriptorError if it is not one).

    The descriptors come back as one float32 matrix, whatever their storage dtype.
    """
    p = Path(path)
    try:
        with pq.ParquetFile(p, pre_buffer=False) as pf:
            schema = pf.schema_arrow
            meta, extra, version, whitening = _meta_from_schema(schema.metadata, p)
            required = ("topic", "frame_index", "log_time_ns", "stamp_ns", "descriptor")
            missing = [c for c in required if c not in schema.names]
            if missing:
                raise DescriptorError(f"{p} lacks column(s) {', '.join(missing)}")
            _check_descriptor_field(schema, meta.dim, p)
            desc = _read_matrix(pf, pf.metadata.num_rows, meta.dim, p)
            patches, patch_pca = _read_patches(pf, schema, p)
        table = pq.read_table(p, columns=[c for c in schema.names if c not in ("descriptor", "patches")],
                              read_dictionary=["topic"])
        pa.default_memory_pool().release_unused()  # hand the batches' memory back before the caller's work
    except (OSError, pa.ArrowException) as exc:
        raise DescriptorError(f"could not read descriptor table {p}: {exc}") from None

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
        topic=_strings(table.column("topic"), p),
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
        moving_index=ints("moving_index") if "moving_index" in table.column_names else None,
        patches=patches,
        patch_pca=patch_pca,
    )


def _read_patches(pf: pq.ParquetFile, schema: pa.Schema, path: Path
                  ) -> tuple[npt.NDArray[np.float16] | None, PatchPCA | None]:
    """The ``patches`` column as ``[n, P, d]`` float16 (filled batch by batch) and the PCA that
    projected them; (None, None) in a file without patches."""
    if "patches" not in schema.names:
        return None, None
    md = schema.metadata or {}
    try:
        shape = tuple(int(v) for v in json.loads(md[b"memlog.patch_shape"]))
        pca = PatchPCA.from_json(md[b"memlog.patch_pca"]) if b"memlog.patch_pca" in md else None
    except (KeyError, ValueError, TypeError) as exc:
        raise DescriptorError(f"{path}: invalid patch metadata: {exc}") from None
    except DescriptorError as exc:
        raise DescriptorError(f"{path}: {exc}") from None
    typ = schema.field("patches").type
    if (len(shape) != 2 or not pa.types.is_fixed_size_list(typ) or typ.value_type != pa.float16()
            or typ.list_size != shape[0] * shape[1] or (pca is not None and shape[1] != pca.dim)):
        raise DescriptorError(f"{path}: patches column {typ} does not match its metadata (shape {shape})")
    n = pf.metadata.num_rows
    out = _read_matrix(pf, n, shape[0] * shape[1], path, "patches", np.float16)
    return out.reshape(n, *shape), pca


def _strings(col: pa.ChunkedArray, path: Path) -> list[str]:
    """A dictionary-encoded string column as a list of str, one Python object per distinct value."""
    if col.null_count:
        raise DescriptorError(f"{path}: column topic has nulls")
    out: list[str] = []
    for chunk in col.chunks:
        if pa.types.is_dictionary(chunk.type):
            words = np.array(chunk.dictionary.to_pylist(), dtype=object)
            out.extend(words[chunk.indices.to_numpy(zero_copy_only=False)].tolist())
        else:
            out.extend(str(t) for t in chunk.to_pylist())
    return out


def read_cached(path: str | os.PathLike[str], log: str | os.PathLike[str], meta: DescriptorMeta,
                window: FrameWindow,
                still_distance: float = STILL_DISTANCE, *, patches: bool = False,
                patch_pca: PatchPCA | None = None) -> DescriptorTable | None:
    """The descriptor table cached at ``path`` when ``describe_log`` made it from ``log`` (same
    identity: path, size, modification time), with ``window``, a describer compatible with
    ``meta`` and the frames' ``moving_index``, its stops found as they are now with
    ``still_distance`` (``extra["stops"]``, :func:`~memlog.scoring.motion.stops_found_otherwise`:
    by the same rule, from the log's motion when it has any), and, with ``patches``, the frames'
    patch features (raw, or projected by ``patch_pca`` when given); else None, saying why
    (``window.topics`` None: the topics the table was made from)."""
    p = Path(path)
    if not p.is_file():
        return None
    try:
        t = read_descriptors(p)
        check_compatible(meta, t.meta)
    except DescriptorError as exc:
        info(f"not reusing {p}: {exc}")
        return None
    if not same_identity(t.extra.get("log_identity"), log):
        info(f"not reusing {p}: it was made from another log (or {log} changed)")
        return None
    topics = window.topics if window.topics is not None else tuple(t.extra.get("window", {}).get("topics") or ())
    if t.extra.get("window") != FrameWindow(tuple(topics), window.start_ns, window.end_ns, window.stride).to_dict():
        info(f"not reusing {p}: it was made with other topics, time window or stride")
        return None
    if t.moving_index is None:
        info(f"not reusing {p}: it has no moving_index (written before stops were recorded)")
        return None
    how = stops_found_otherwise(t.extra, still_distance)
    if how is not None:
        info(f"not reusing {p}: its stops were found {how}")
        return None
    if patches and (t.patches is None or (t.patch_pca.sha256 if t.patch_pca is not None else None)
                    != (patch_pca.sha256 if patch_pca is not None else None)):
        info(f"not reusing {p}: it has no patch features" + (" in the map's PCA space" if t.patches is not None else ""))
        return None
    info(f"reusing descriptors {p} (same log, window and descriptor)")
    return t
