"""MCAP writer: copies every record of an input log and adds memlog's own channels.

Output goes through :class:`~memlog.io.atomic.AtomicFile` (a temporary file beside the target,
renamed over it only when :meth:`McapLogWriter.close` completes), so an interrupted run never
leaves a half file under the final name. zstd chunks, CRCs, summary and indexes are on by default.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from types import TracebackType
from typing import Any

from mcap.writer import CompressionType, Writer

from memlog._version import __version__
from memlog.errors import LogWriteError
from memlog.io.atomic import AtomicFile
from memlog.io.base import LogReader
from memlog.io.records import ChannelInfo, RawMessage

__all__ = ["McapLogWriter", "copy_log", "CopyStats"]

_LOG = logging.getLogger("memlog.io")

_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class McapLogWriter:
    """Write an MCAP file atomically.

    ``add_schema``/``add_channel`` deduplicate identical definitions; ``channel_for``
    maps an input :class:`ChannelInfo` to an output channel id (registering it once), so
    passthrough of another log is ``writer.write_raw(msg)`` per message. :meth:`register_input`
    registers an input log's schemas and channels first, in the order of their ids, so that they
    keep them: the ``mcap`` library numbers schemas and channels 1, 2, 3... as they come, so an
    id is kept when the input's ids run from 1 without a gap (as every MCAP writer numbers them);
    the others are numbered anew (said in the log). New JSON channels come from
    ``add_json_channel`` + ``write_json``.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        profile: str = "",
        compression: str = "zstd",
        chunk_size: int = 4 * 1024 * 1024,
        library: str | None = None,
    ) -> None:
        self.path = Path(path)
        if compression not in _COMPRESSION:
            raise LogWriteError(f"unknown compression {compression!r} (zstd, lz4, none)")
        self._file = AtomicFile(self.path)
        self._fh = self._file.fh
        self._writer = Writer(
            self._fh, chunk_size=chunk_size, compression=_COMPRESSION[compression], enable_crcs=True,
            enable_data_crcs=True,
        )
        self._writer.start(profile=profile, library=library or f"memlog {__version__}")
        self._schemas: dict[int, tuple[str, str, bytes]] = {}  # id -> definition, as the library numbered them
        self._channels: dict[int, tuple[str, str, int, tuple[tuple[str, str], ...]]] = {}
        self._in_map: dict[tuple[Any, ...], int] = {}
        self.messages_written = 0
        self._closed = False
        self._finished = False

    # -- registration -----------------------------------------------------------
    def add_schema(self, name: str, encoding: str, data: bytes, schema_id: int = 0) -> int:
        """The id of the schema record ``name``/``encoding``/``data``, registered on first use.
        ``schema_id``: the id it should keep (an input's); where the library's next id is not it,
        an identical schema's id serves, else the next id."""
        key = (name, encoding, bytes(data))
        return _register(self._schemas, key, schema_id or None,
                         lambda: self._writer.register_schema(name, encoding, key[2]))

    def add_channel(
        self, topic: str, message_encoding: str, schema_id: int, metadata: Mapping[str, str] | None = None,
        channel_id: int | None = None,
    ) -> int:
        """The id of the channel record, registered on first use (``channel_id`` as
        :meth:`add_schema`'s ``schema_id``)."""
        meta = dict(metadata or {})
        key = (topic, message_encoding, schema_id, tuple(sorted(meta.items())))
        return _register(self._channels, key, channel_id,
                         lambda: self._writer.register_channel(topic, message_encoding, schema_id, meta))

    def register_input(self, reader: LogReader) -> None:
        """Register ``reader``'s schemas, then its channels, each in the order of their ids
        (before anything else is registered, they keep their ids: see the class doc); an MCAP
        channel that cannot keep its id is named in the log (a bag's connection ids are no
        channel ids)."""
        channels = sorted(reader.channels(), key=lambda c: c.id)
        schemas = {c.schema.id: c.schema for c in channels if c.schema is not None and c.schema.id}
        for sid in sorted(schemas):
            s = schemas[sid]
            self.add_schema(s.name, s.encoding, s.data, sid)
        for ch in channels:
            cid = self.channel_for(ch)
            if cid != ch.id and reader.format == "mcap":
                _LOG.info("%s: channel %d (%s) is written as channel %d", self.path, ch.id, ch.topic, cid)

    def channel_for(self, channel: ChannelInfo, source: str = "") -> int:
        """Output channel id of an input channel (registered with the same schema on first use).
        Keyed on the channel's content too: a reader that corrects a channel from the data (its
        index said otherwise) hands out a new ChannelInfo with the same id."""
        key = (source, channel.id, channel.topic, channel.message_encoding, channel.schema)
        cid = self._in_map.get(key)
        if cid is None:
            sid = 0
            if channel.schema is not None:
                s = channel.schema
                sid = self.add_schema(s.name, s.encoding, s.data, s.id)
            cid = self._in_map[key] = self.add_channel(channel.topic, channel.message_encoding, sid, channel.metadata,
                                                       channel.id)
        return cid

    def add_json_channel(self, topic: str, schema_name: str, schema: Mapping[str, Any] | bytes) -> int:
        data = schema if isinstance(schema, bytes) else json.dumps(schema, indent=1).encode()
        sid = self.add_schema(schema_name, "jsonschema", data)
        return self.add_channel(topic, "json", sid)

    # -- records ------------------------------------------------------------------
    def write(self, channel_id: int, log_time: int, data: bytes, publish_time: int | None = None, sequence: int = 0) -> None:
        self._writer.add_message(
            channel_id=channel_id, log_time=log_time, data=data,
            publish_time=log_time if publish_time is None else publish_time, sequence=sequence,
        )
        self.messages_written += 1

    def write_raw(self, msg: RawMessage, source: str = "") -> None:
        """Pass one input message through with its bytes, times and sequence untouched."""
        self.write(self.channel_for(msg.channel, source), msg.log_time, msg.data, msg.publish_time, msg.sequence)

    def write_json(self, channel_id: int, log_time: int, obj: Any, publish_time: int | None = None) -> None:
        self.write(channel_id, log_time, json.dumps(obj, separators=(",", ":"), allow_nan=False).encode(), publish_time)

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def add_attachment(self, name: str, media_type: str, data: bytes, log_time: int = 0, create_time: int = 0) -> None:
        self._writer.add_attachment(create_time=create_time, log_time=log_time, name=name, media_type=media_type, data=data)

    # -- finish -------------------------------------------------------------------
    def finish(self) -> AtomicFile:
        """Finish the file (summary, indexes) under its temporary name (``.tmp`` of the returned
        file, flushed) without moving it into place: the caller commits it (or aborts it), for
        example together with a companion file (:func:`~memlog.io.atomic.commit_together`)."""
        if self._closed:
            raise LogWriteError(f"{self.path}: the writer is already closed")
        if not self._finished:
            try:
                self._writer.finish()  # type: ignore[no-untyped-call]
                self._fh.flush()
            except BaseException:
                self.abort()
                raise
            self._finished = True
        return self._file

    def close(self) -> Path:
        """Finish the file (summary, indexes) and move it to its final name."""
        if self._closed:
            return self.path
        try:
            self.finish().commit()
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return self.path

    def abort(self) -> None:
        """Drop the temporary file; the target is left as it was."""
        if self._closed:
            return
        self._closed = True
        self._file.abort()

    def __enter__(self) -> "McapLogWriter":
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        if et is None:
            self.close()
        else:
            self.abort()


def _register(table: dict[int, Any], key: Any, wanted: int | None, register: Callable[[], int]) -> int:
    """The id of a record with definition ``key`` in ``table`` (id -> definition, as the library
    numbered them): ``wanted`` when it holds that definition, or when it is the id the library
    gives next (``register`` registers the record and returns its id); else an id that holds the
    same definition, else the next id."""
    if wanted is not None and table.get(wanted) == key:
        return wanted
    if wanted != len(table) + 1:
        same = next((i for i, k in table.items() if k == key), None)
        if same is not None:
            return same
    got = register()
    table[got] = key
    return got


class CopyStats:
    """Counts of what :func:`copy_log` passed through."""

    def __init__(self) -> None:
        self.messages = 0
        self.bytes = 0
        self.metadata = 0
        self.attachments = 0


def copy_log(
    reader: LogReader,
    writer: McapLogWriter,
    *,
    log_time_order: bool = False,
    wrap: Callable[[Iterator[RawMessage]], Iterator[RawMessage]] | None = None,
) -> CopyStats:
    """Copy every schema, channel, message, metadata and attachment record of ``reader``.

    Channels are registered up front (so channels without messages survive); ``wrap`` wraps the
    message stream (a progress bar). Messages stream in file order unless ``log_time_order``.
    """
    stats = CopyStats()
    writer.register_input(reader)
    stream = reader.messages(log_time_order=log_time_order)
    for msg in wrap(stream) if wrap is not None else stream:
        writer.write_raw(msg)
        stats.messages += 1
        stats.bytes += len(msg.data)
    for name, data in reader.metadata():
        writer.add_metadata(name, data)
        stats.metadata += 1
    for att in reader.attachments():
        writer.add_attachment(att.name, att.media_type, att.data, att.log_time, att.create_time)
        stats.attachments += 1
    return stats
