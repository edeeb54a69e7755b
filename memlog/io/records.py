"""Format-neutral records streamed by every reader (schemas, channels, messages)."""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field

__all__ = ["SchemaInfo", "ChannelInfo", "RawMessage", "Attachment", "ReadReport"]


@dataclass(frozen=True)
class SchemaInfo:
    """A message schema as stored in the log (``encoding``: ros1msg, ros2msg, ros2idl,
    jsonschema, protobuf, or "" for none). ``id``: the MCAP schema record's id (0 where the log
    has none, as in a bag); two schemas that differ only in their ids compare equal."""

    name: str
    encoding: str
    data: bytes
    id: int = field(default=0, compare=False)


@dataclass(frozen=True)
class ChannelInfo:
    """A channel (MCAP) or connection (bag): topic, message encoding and schema."""

    id: int
    topic: str
    message_encoding: str
    schema: SchemaInfo | None
    metadata: dict[str, str] = field(default_factory=dict, hash=False, compare=False)

    @property
    def msgtype(self) -> str:
        return self.schema.name if self.schema else ""


@dataclass(frozen=True)
class RawMessage:
    """One message with its serialized bytes untouched.

    ``where`` is where the reader found it, ``(container, offset)``: the file offset of the chunk
    (or of the record, the row id) and the message's offset inside it; the readers' frame tables
    (:class:`~memlog.io.frame_table.FrameTable`) are keyed on it. None for messages made elsewhere.
    """

    channel: ChannelInfo
    log_time: int
    publish_time: int
    sequence: int
    data: bytes
    where: tuple[int, int] | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Attachment:
    """An MCAP attachment record."""

    name: str
    media_type: str
    log_time: int
    create_time: int
    data: bytes


@dataclass
class ReadReport:
    """What went wrong while reading, kept so a run can report it at the end.

    ``truncated`` is set when the log ended early (or a damaged region stopped the read);
    ``bytes_read`` says how far the reader got; ``index_damaged`` when the log's index (MCAP
    summary, bag index, ROS 2 metadata) is unreadable or disagrees with the data, which was
    read instead; ``skipped_files`` counts storage files of a ROS 2 bag that could not be read
    at all; ``retimed_messages`` counts messages kept although the log's time for them was
    damaged (a ROS 2 ``.db3`` row whose timestamp is not a time): they carry their header stamp,
    else a neighbouring message's time; ``data_crc_failed`` when a checksum over records read
    whole fails (an unchunked MCAP's data-section CRC): they were kept, but which of them is
    damaged cannot be told; ``warnings`` are human-readable lines that name the
    file, topic and message index.
    """

    path: str
    truncated: bool = False
    bytes_read: int | None = None
    skipped_chunks: int = 0
    bad_messages: int = 0
    undecodable_frames: int = 0
    index_damaged: bool = False
    skipped_files: int = 0
    retimed_messages: int = 0
    data_crc_failed: bool = False
    warnings: list[str] = field(default_factory=list)
    places: set[tuple[str, Hashable]] = field(default_factory=set, repr=False, compare=False)

    def warn(self, text: str) -> None:
        if text not in self.warnings:
            self.warnings.append(text)

    def count(self, kind: str, place: Hashable) -> bool:
        """Count one damaged ``place`` (a chunk's offset, a message's location) under ``kind``
        (``skipped_chunks``, ``bad_messages``, ``undecodable_frames``, ``skipped_files``,
        ``retimed_messages``), once:
        a second pass over the same damage is not new damage. Returns whether it was new."""
        key = (kind, place)
        if key in self.places:
            return False
        self.places.add(key)
        setattr(self, kind, getattr(self, kind) + 1)
        return True

    def merge(self, other: "ReadReport") -> None:
        """Add what ``other`` (another reader of the same log: a worker, an earlier pass) found;
        damage both found at the same place counts once."""
        self.truncated |= other.truncated
        self.index_damaged |= other.index_damaged
        self.data_crc_failed |= other.data_crc_failed
        if other.bytes_read is not None:
            self.bytes_read = other.bytes_read if self.bytes_read is None else min(self.bytes_read, other.bytes_read)
        for kind in ("skipped_chunks", "bad_messages", "undecodable_frames", "skipped_files", "retimed_messages"):
            placed = [p for k, p in other.places if k == kind]
            unplaced = getattr(other, kind) - len(placed)  # counted without a place: always added
            setattr(self, kind, getattr(self, kind) + max(0, unplaced))
            for place in placed:
                self.count(kind, place)
        for w in other.warnings:
            self.warn(w)

    @property
    def ok(self) -> bool:
        return not (self.truncated or self.skipped_chunks or self.bad_messages or self.undecodable_frames
                    or self.index_damaged or self.skipped_files or self.retimed_messages or self.data_crc_failed)

    def damage(self) -> list[str]:
        """What was damaged, one phrase each (empty when :attr:`ok`)."""
        parts = []
        if self.truncated:
            parts.append(f"log truncated (read up to byte {self.bytes_read})" if self.bytes_read else "log truncated")
        if self.skipped_chunks:
            parts.append(f"{self.skipped_chunks} damaged chunk(s) skipped")
        if self.bad_messages:
            parts.append(f"{self.bad_messages} message(s) did not deserialize")
        if self.undecodable_frames:
            parts.append(f"{self.undecodable_frames} frame(s) did not decode")
        if self.skipped_files:
            parts.append(f"{self.skipped_files} unreadable storage file(s) skipped")
        if self.retimed_messages:
            parts.append(f"{self.retimed_messages} message(s) without a valid log time kept at their header stamp "
                         "(else a neighbour's time)")
        if self.data_crc_failed:
            parts.append("the data section fails its CRC check (its records were kept; which of them is damaged "
                         "cannot be told)")
        if self.index_damaged:
            parts.append("its index is damaged or disagrees with the data (the data was read)")
        return parts
