"""Format-neutral records streamed by every reader (schemas, channels, messages)."""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["SchemaInfo", "ChannelInfo", "RawMessage", "Attachment", "ReadReport"]


@dataclass(frozen=True)
class SchemaInfo:
    """A message schema as stored in the log (``encoding``: ros1msg, ros2msg, ros2idl,
    jsonschema, protobuf, or "" for none)."""

    name: str
    encoding: str
    data: bytes


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
    """One message with its serialized bytes untouched."""

    channel: ChannelInfo
    log_time: int
    publish_time: int
    sequence: int
    data: bytes


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
    at all; ``warnings`` are human-readable lines that name the file, topic and message
    index.
    """

    path: str
    truncated: bool = False
    bytes_read: int | None = None
    skipped_chunks: int = 0
    bad_messages: int = 0
    undecodable_frames: int = 0
    index_damaged: bool = False
    skipped_files: int = 0
    warnings: list[str] = field(default_factory=list)

    def warn(self, text: str) -> None:
        self.warnings.append(text)

    @property
    def ok(self) -> bool:
        return not (self.truncated or self.skipped_chunks or self.bad_messages or self.undecodable_frames
                    or self.index_damaged or self.skipped_files)

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
        if self.index_damaged:
            parts.append("its index is damaged or disagrees with the data (the data was read)")
        return parts
