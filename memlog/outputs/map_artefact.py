"""A memorable map as one artefact: the map log ``MAP.mcap`` and its reference descriptors
``MAP.parquet``, each recording the other, put in place together.

**How each records the other.** Each file's sha256 would depend on the other's, so the two
directions hash different things:

* the Parquet records the map's **file** sha256 (every byte of ``MAP.mcap``) and its file name
  when written, in schema metadata ``memlog.map_sha256`` and ``memlog.map_file``;
* the map records the descriptor table's **content** sha256 (:func:`descriptor_content_sha256`)
  and the Parquet's file name when written, in the MCAP metadata record
  ``memlog_map_descriptors`` (keys ``scheme`` = ``"1"``, ``descriptors_sha256``,
  ``descriptors_file``; both empty for a map written without descriptors).

The content sha256 covers what the table says, not how Parquet encoded it: the row count, every
``memlog.*`` schema metadata entry but the two map keys above (what made the descriptors, the
whitening transform, ``memlog.extra``...), and every column by name in file order: its values
(the descriptors' stored elements, float32 or float16, as little-endian bytes; numbers as
little-endian bytes with nulls as zero; strings length-prefixed UTF-8) and which rows are null.
It leaves out the map keys, so it is known before the map is finished: :func:`write_map` builds
the table in memory, hashes its content, finishes the map with that record (under a temporary
name), hashes the finished map file, and writes the Parquet (under a temporary name) with that
hash. Both directions are checked from the files alone by :func:`check_map_pair`: the map file's
sha256 is the one the Parquet records, and the content sha256 of the Parquet as read is the one
the map records (a table from another run fails the first; a table changed after the map was
written fails the second).

**Putting them in place** (:func:`~memlog.io.atomic.commit_together`). Nothing is renamed until
both files are complete; a failure before (describing, writing either file) leaves the old pair
as it was. Then the old Parquet is moved aside, the map renamed into place, the Parquet renamed
into place, the old Parquet removed. A failed rename is undone: the old Parquet is moved back
when the map's rename failed (the old pair is as it was), and the new map is removed when the
Parquet's rename failed (neither file is left: the old map was replaced). The remaining window
is a crash (power loss, SIGKILL) between the renames, which leaves a map without its Parquet (and
the old Parquet as a hidden ``.MAP.parquet.*.old`` beside): never a new map beside an old
Parquet. A map written without descriptors removes, with its commit, a Parquet beside it (or
at the descriptor path given) that names the map it replaces (by sha256) or a map of its file
name, so no stale pair is left either.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from memlog.descriptors.table import DescriptorTable
from memlog.errors import DescriptorError
from memlog.io.atomic import AtomicFile, commit_together, same_path
from memlog.io.identity import sha256_file
from memlog.io.open import open_log
from memlog.outputs.descriptor_table import ROW_GROUP_BYTES, descriptor_arrow, write_arrow
from memlog.outputs.maplog import MapLogWriter
from memlog.progress import info

__all__ = ["MapPairError", "check_map_pair", "write_map", "descriptor_content_sha256",
           "LINK_RECORD", "MAP_SHA256", "MAP_FILE"]

SCHEME = "1"
#: The map's metadata record naming its descriptor table.
LINK_RECORD = "memlog_map_descriptors"
#: The Parquet's schema metadata keys naming its map.
MAP_SHA256 = b"memlog.map_sha256"
MAP_FILE = b"memlog.map_file"
_LINK_KEYS = (MAP_SHA256, MAP_FILE)

PathLike = str | os.PathLike[str]


class MapPairError(DescriptorError):
    """A descriptor table does not belong to the map it is used with (or cannot be checked)."""




def _frame(h: "hashlib._Hash", data: bytes) -> None:
    h.update(len(data).to_bytes(8, "little"))
    h.update(data)


class _ColumnDigest:
    """The sha256 of one column fed chunk by chunk: the same whatever the chunking (one stream
    per part: validity, values, and a list's child values)."""

    def __init__(self) -> None:
        self.streams: dict[str, hashlib._Hash] = {}
        self.types: dict[str, set[str]] = {}

    def _h(self, path: str, kind: str) -> "hashlib._Hash":
        self.types.setdefault(path, set()).add(kind)
        if path not in self.streams:
            self.streams[path] = hashlib.sha256()
        return self.streams[path]

    def add(self, arr: pa.Array, path: str = "") -> None:
        if pa.types.is_dictionary(arr.type):
            arr = arr.dictionary_decode()
        t = arr.type
        valid = np.asarray(arr.is_valid().to_numpy(zero_copy_only=False), dtype=np.uint8)
        self._h(path + "valid", "bool").update(valid.tobytes())
        if pa.types.is_fixed_size_list(t) and not arr.null_count:
            self._h(path + "list", f"fixed_size_list[{t.list_size}]")
            self.add(arr.flatten(), path + "values/")
        elif pa.types.is_string(t) or pa.types.is_large_string(t):
            h = self._h(path + "values", "string")
            for v in arr.to_pylist():
                if v is not None:
                    _frame(h, v.encode())
        elif pa.types.is_integer(t) or pa.types.is_floating(t) or pa.types.is_boolean(t):
            filled = arr.fill_null(pa.scalar(False if pa.types.is_boolean(t) else 0, t)) if arr.null_count else arr
            vals = np.ascontiguousarray(filled.to_numpy(zero_copy_only=False))
            self._h(path + "values", str(t)).update(vals.astype(vals.dtype.newbyteorder("<"), copy=False).tobytes())
        else:  # (no such column today) anything else: its values as JSON
            h = self._h(path + "values", "json")
            for v in arr.to_pylist():
                _frame(h, json.dumps(v, sort_keys=True, default=str).encode())

    def digest(self) -> bytes:
        h = hashlib.sha256()
        for path in sorted(self.streams):
            _frame(h, path.encode())
            _frame(h, ",".join(sorted(self.types[path])).encode())
            _frame(h, self.streams[path].digest())
        return h.digest()


def _content_sha256(metadata: Mapping[bytes, bytes] | None, names: list[str], rows: int,
                    chunks: Callable[[str], Iterable[pa.Array]]) -> str:
    h = hashlib.sha256()
    _frame(h, f"memlog descriptor content {SCHEME}".encode())
    _frame(h, str(rows).encode())
    md = {k: v for k, v in (metadata or {}).items() if k.startswith(b"memlog.") and k not in _LINK_KEYS}
    for k in sorted(md):
        _frame(h, k)
        _frame(h, md[k])
    for name in names:
        col = _ColumnDigest()
        for arr in chunks(name):
            col.add(arr)
        _frame(h, name.encode())
        _frame(h, col.digest())
    return h.hexdigest()


def descriptor_content_sha256(source: pa.Table | PathLike) -> str:
    """The content sha256 of a descriptor table (see module doc): of an Arrow table made by
    :func:`~memlog.outputs.descriptor_table.descriptor_arrow`, or of the Parquet file at
    ``source`` (read column by column in batches; DescriptorError if it cannot be read)."""
    if isinstance(source, pa.Table):
        table = source
        return _content_sha256(table.schema.metadata, table.schema.names, table.num_rows,
                               lambda name: table.column(name).chunks)
    p = Path(source)
    try:
        with pq.ParquetFile(p, pre_buffer=False) as pf:
            schema = pf.schema_arrow

            def chunks(name: str) -> Iterable[pa.Array]:
                for batch in pf.iter_batches(batch_size=max(1, ROW_GROUP_BYTES // 4096), columns=[name],
                                             use_threads=False):
                    yield batch.column(0)

            return _content_sha256(schema.metadata, schema.names, pf.metadata.num_rows, chunks)
    except (OSError, pa.ArrowException) as exc:
        raise DescriptorError(f"could not read descriptor table {p}: {exc}") from None


def _recorded_map(path: Path) -> tuple[str, str] | None:
    """The map sha256 and file name a Parquet records (None: it records none; DescriptorError:
    it cannot be read)."""
    try:
        md = pq.read_schema(path).metadata or {}
    except (OSError, pa.ArrowException) as exc:
        raise DescriptorError(f"could not read descriptor table {path}: {exc}") from None
    if MAP_SHA256 not in md:
        return None
    return md[MAP_SHA256].decode(errors="replace"), md.get(MAP_FILE, b"").decode(errors="replace")


def _names_map(path: Path, map_path: Path) -> bool:
    """Whether ``path`` is a descriptor table made for the map now at ``map_path`` (by its
    sha256) or for a map of its file name."""
    if not path.is_file():
        return False
    try:
        rec = _recorded_map(path)
    except DescriptorError:
        return False
    if rec is None:
        return False
    if rec[1] == map_path.name:
        return True
    try:
        return map_path.is_file() and sha256_file(map_path) == rec[0]
    except OSError:
        return False


def write_map(writer: MapLogWriter, metadata: Mapping[str, str], descriptors: PathLike | None = None,
              table: DescriptorTable | None = None, *, dtype: str = "float32") -> None:
    """Finish the map of ``writer`` (``metadata``: its ``memlog_map`` record) and write its
    descriptor ``table`` to ``descriptors`` (stored as ``dtype``) as one artefact: each records
    the other and both are put in place together, or neither is (see module doc). ``table``
    None: a map without descriptors; a Parquet at ``descriptors`` (or beside the map) that names
    the map replaced or a map of this file name is removed with the commit. On any failure the
    writer's temporary file is dropped too (the exception propagates)."""
    dpath = Path(descriptors) if descriptors is not None else None
    if table is not None and dpath is None:
        raise DescriptorError(f"{writer.path}: a descriptor table needs a path")
    arrow = descriptor_arrow(table, dtype=dtype) if table is not None else None
    writer.add_metadata(LINK_RECORD, {
        "scheme": SCHEME,
        "descriptors_sha256": descriptor_content_sha256(arrow) if arrow is not None else "",
        "descriptors_file": dpath.name if arrow is not None and dpath is not None else "",
    })
    parts = [writer.finish(metadata)]
    try:
        stale: list[Path] = []
        candidates = [writer.path.with_suffix(".parquet")] + ([dpath] if arrow is None and dpath is not None else [])
        for c in candidates:
            if not (arrow is not None and dpath is not None and same_path(c, dpath)) and not same_path(c, writer.path) \
                    and c not in stale and _names_map(c, writer.path):
                stale.append(c)
        if arrow is not None and dpath is not None:
            link = {MAP_SHA256: sha256_file(parts[0].tmp).encode(), MAP_FILE: writer.path.name.encode()}
            arrow = arrow.replace_schema_metadata({**(arrow.schema.metadata or {}), **link})
            parts.append(AtomicFile(dpath))
            try:
                write_arrow(parts[1].fh, arrow)
            except (OSError, pa.ArrowException) as exc:
                raise DescriptorError(f"could not write {dpath}: {exc}") from None
        commit_together(parts, stale)
    except BaseException:
        for f in parts:
            f.abort()
        raise
    for s in stale:
        info(f"removed {s}: the descriptor table of the map {writer.path} replaced (this map has "
             f"{'its table at ' + str(dpath) if arrow is not None else 'no descriptors'})")


def _map_record(path: Path) -> dict[str, str] | None:
    """The map's ``memlog_map_descriptors`` record (None: it has none)."""
    with open_log(path) as reader:
        for name, data in reader.metadata():
            if name == LINK_RECORD:
                return data
    return None


def check_map_pair(map_mcap: PathLike, parquet: PathLike) -> None:
    """Check that the descriptor table ``parquet`` belongs to the map ``map_mcap`` (both were
    written by one ``memlog map`` run and neither changed since; see module doc).

    Raises :class:`MapPairError` (a :class:`~memlog.errors.DescriptorError`) naming both files
    when it does not, or when one of them records no link (written by an older memlog, or the
    map without descriptors); DescriptorError / LogReadError when a file cannot be read."""
    m, p = Path(map_mcap), Path(parquet)
    rec = _recorded_map(p)
    if rec is None:
        raise MapPairError(f"{p} does not record the map it belongs to (written by an older memlog, or not by "
                           f"`memlog map`), so it cannot be checked against the map {m}")
    link = _map_record(m)
    if link is None:
        raise MapPairError(f"the map {m} records no descriptor table (written by an older memlog, or not by "
                           f"`memlog map`), so {p} cannot be checked against it")
    want_map, map_name = rec
    if not link.get("descriptors_sha256"):
        raise MapPairError(f"{p} does not belong to the map {m}: that map was written without descriptors "
                           f"({p} was written for a map {map_name or '?'} of sha256 {want_map[:12]}…)")
    have_map = sha256_file(m)
    if have_map != want_map:
        raise MapPairError(
            f"{p} does not belong to the map {m}: it was written for a map {map_name or '?'} of sha256 "
            f"{want_map[:12]}…, and {m} has sha256 {have_map[:12]}… (a map of another run, or a changed file; "
            f"{m}'s own table was written as {link.get('descriptors_file') or '?'})")
    want_content = link["descriptors_sha256"]
    have_content = descriptor_content_sha256(p)
    if have_content != want_content:
        raise MapPairError(
            f"the map {m} does not belong to {p}: {p} names that map, but the map was written with a descriptor "
            f"table ({link.get('descriptors_file') or '?'}) of content sha256 {want_content[:12]}…, and {p} holds "
            f"{have_content[:12]}… (the table changed after the map was written)")
