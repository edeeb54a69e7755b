"""The reader interface every log format implements, and the frame stream built on it."""

from __future__ import annotations

import os
import sys
from abc import ABC, abstractmethod
from collections.abc import Callable, Container, Iterable, Iterator, Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from memlog.errors import ConfigError, ImageDecodeError, TopicError
from memlog.io.camera import camera_kind, extract_image
from memlog.io.decoders import UnsupportedEncoding, make_deserializer
from memlog.io.frame import Frame
from memlog.io.records import Attachment, ChannelInfo, RawMessage, ReadReport
from memlog.io.types import LogInfo, TopicInfo

__all__ = ["LogReader", "FrameError", "StreamItem", "FrameWindow"]


class FrameError:
    """A camera message that could not be turned into a frame (kept for the run report)."""

    def __init__(self, path: str, topic: str, index: int, log_time: int, reason: str) -> None:
        self.path, self.topic, self.index, self.log_time, self.reason = path, topic, index, log_time, reason

    def __str__(self) -> str:
        return f"{self.path}: topic {self.topic} message {self.index} (log time {self.log_time}): {self.reason}"


@dataclass(frozen=True)
class StreamItem:
    """One record of :meth:`LogReader.stream`.

    For a camera message: ``index`` is its position on its topic (from 0, log-time order, counted
    from the start of the log whatever the window), ``frame`` the deserialized frame (None when
    the message does not deserialize: it was reported). For a passthrough message (a topic
    named in ``passthrough``): ``index`` and ``frame`` are None.
    """

    raw: RawMessage
    index: int | None = None
    frame: Frame | None = None


@dataclass(frozen=True)
class FrameWindow:
    """Which camera frames a step reads: ``topics`` (None: every camera topic), the log-time
    window [``start_ns``, ``end_ns``) and every ``stride``-th frame of each topic."""

    topics: tuple[str, ...] | None = None
    start_ns: int | None = None
    end_ns: int | None = None
    stride: int = 1

    def __post_init__(self) -> None:
        if isinstance(self.stride, bool) or not isinstance(self.stride, int) or self.stride < 1:
            raise ConfigError(f"stride must be an integer >= 1, got {self.stride!r}")
        if self.start_ns is not None and self.end_ns is not None and self.end_ns <= self.start_ns:
            raise ConfigError(f"the time window is empty: end {self.end_ns} <= start {self.start_ns}")
        if self.topics is not None:
            object.__setattr__(self, "topics", tuple(self.topics))

    def to_dict(self) -> dict[str, Any]:
        return {"topics": list(self.topics) if self.topics is not None else None, "start_ns": self.start_ns,
                "end_ns": self.end_ns, "stride": self.stride}


def _warn_stderr(text: str) -> None:
    print(f"memlog: warning: {text}", file=sys.stderr)


class LogReader(ABC):
    """A log opened for streaming. Use :func:`memlog.io.open_log` to get one.

    Subclasses implement :meth:`channels`, :meth:`_iter_messages` and optionally
    :meth:`metadata` / :meth:`attachments`. Everything streams: no method loads the
    whole log.
    """

    format: str = ""
    profile: str = ""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = os.fspath(path)
        self.report = ReadReport(self.path)
        self.on_warning: Callable[[str], None] = _warn_stderr

    # -- to implement -------------------------------------------------------------
    @abstractmethod
    def channels(self) -> list[ChannelInfo]:
        """All channels/connections of the log."""

    @abstractmethod
    def _iter_messages(
        self, topics: set[str] | None, start_ns: int | None, end_ns: int | None, log_time_order: bool
    ) -> Iterator[RawMessage]:
        """Messages with their untouched bytes."""

    def metadata(self) -> Iterator[tuple[str, dict[str, str]]]:
        """Metadata records (MCAP only)."""
        return iter(())

    def attachments(self) -> Iterator[Attachment]:
        """Attachment records (MCAP only)."""
        return iter(())

    def message_counts(self) -> dict[int, int] | None:
        """Messages per channel id from an index, or None when only a full scan can tell."""
        return None

    def checksums(self) -> str:
        """What the data read so far was checked against: ``"all"`` (every chunk had a CRC and
        was checked), ``"some"``, ``"none"`` (the format or file has no checksums: flipped bytes
        cannot be detected) or ``"unknown"`` (nothing read yet)."""
        return "none"

    def close(self) -> None:
        """Release the file."""

    # -- shared ---------------------------------------------------------------------
    def __enter__(self) -> "LogReader":
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    def warn(self, text: str) -> None:
        self.report.warn(text)
        self.on_warning(text)

    @property
    def size_bytes(self) -> int:
        if os.path.isdir(self.path):
            return sum(
                os.path.getsize(os.path.join(root, f)) for root, _, files in os.walk(self.path) for f in files
            )
        return os.path.getsize(self.path)

    def topics(self) -> list[str]:
        return sorted({c.topic for c in self.channels()})

    def camera_topics(self) -> list[str]:
        return sorted({c.topic for c in self.channels() if camera_kind(c.msgtype)})

    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
        log_time_order: bool = True,
    ) -> Iterator[RawMessage]:
        """Stream raw messages, optionally filtered by topic and log-time window [start, end)."""
        wanted = set(topics) if topics is not None else None
        if wanted is not None:
            missing = wanted - set(self.topics())
            if missing:
                raise TopicError(
                    f"{self.path}: no topic {', '.join(sorted(missing))} (topics: {', '.join(self.topics())})"
                )
        it = self._iter_messages(wanted, start_ns, end_ns, log_time_order)
        if start_ns is not None or end_ns is not None:
            return it
        return self._check_counts(it, wanted)

    def _check_counts(self, it: Iterator[RawMessage], topics: set[str] | None) -> Iterator[RawMessage]:
        """Pass ``it`` through; once it has run to its end, compare the messages per channel with
        what the index claims. A difference that no other damage explains means the index lies
        (reported; :attr:`ReadReport.index_damaged`)."""
        index = self.message_counts()
        seen: dict[int, int] = {}
        for m in it:
            cid = m.channel.id
            seen[cid] = seen.get(cid, 0) + 1
            yield m
        if index is None or not self.report.ok:
            return
        wrong = []
        for ch in self.channels():
            if topics is None or ch.topic in topics:
                claimed, found = index.get(ch.id, 0), seen.get(ch.id, 0)
                if claimed != found:
                    wrong.append(f"{ch.topic}: index {claimed}, data {found}")
        if wrong:
            self.report.index_damaged = True
            self.warn(f"{self.path}: the index does not match the data (messages per topic: {'; '.join(wrong)}); "
                      "the data's messages were read")

    def info(self, scan: bool = False) -> LogInfo:
        """Topic table: type, encoding, count and time range. From the index when there is one,
        unless ``scan``: then every message is read (verifying checksums where the format has
        them) and the counts are the data's."""
        counts = None if scan else self.message_counts()
        ranges: dict[int, list[int]] = {}
        if counts is None:
            counts = {}
            for m in self.messages(log_time_order=False):
                cid = m.channel.id
                counts[cid] = counts.get(cid, 0) + 1
                r = ranges.setdefault(cid, [m.log_time, m.log_time])
                r[0] = min(r[0], m.log_time)
                r[1] = max(r[1], m.log_time)
        by_topic: dict[str, TopicInfo] = {}
        for c in self.channels():
            t = by_topic.get(c.topic)
            rng = ranges.get(c.id)
            if t is None:
                t = by_topic[c.topic] = TopicInfo(
                    c.topic, c.msgtype, c.message_encoding, 0, is_camera=camera_kind(c.msgtype) is not None
                )
            t.count += counts.get(c.id, 0)
            if rng:
                t.start_ns = rng[0] if t.start_ns is None else min(t.start_ns, rng[0])
                t.end_ns = rng[1] if t.end_ns is None else max(t.end_ns, rng[1])
        info = LogInfo(self.path, self.format, self.size_bytes, profile=self.profile, topics=list(by_topic.values()))
        if not ranges:
            self._fill_time_range(info)
        starts = [t.start_ns for t in info.topics if t.start_ns is not None]
        ends = [t.end_ns for t in info.topics if t.end_ns is not None]
        if info.start_ns is None and starts:
            info.start_ns, info.end_ns = min(starts), max(ends)
        return info

    def _fill_time_range(self, info: LogInfo) -> None:
        """Hook for formats whose index knows per-topic time ranges."""

    def check_camera_topics(self, topics: Iterable[str] | None) -> list[str]:
        """The camera topics to stream: ``topics`` (checked: each must be a camera topic of
        this log) or, when None, every camera topic. :class:`TopicError` names what is wrong."""
        cams = self.camera_topics()
        if topics is None:
            return cams
        wanted = sorted(set(topics))
        not_cam = set(wanted) - set(cams)
        if not_cam:
            bad = ", ".join(sorted(not_cam))
            if not_cam - set(self.topics()):
                raise TopicError(f"{self.path}: no topic {bad} (camera topics: {', '.join(cams) or 'none'})")
            raise TopicError(f"{self.path}: topic {bad} is not a camera topic (camera topics: {', '.join(cams) or 'none'})")
        return wanted

    def count_frames(self, window: FrameWindow) -> int | None:
        """How many frames :meth:`stream` yields for ``window``, from the index when the log has
        one (None when only a full scan could tell)."""
        counts = self.message_counts()
        if counts is None:
            return None
        windowed = window.start_ns is not None or window.end_ns is not None
        total = 0
        for topic in self.check_camera_topics(window.topics):
            n = sum(counts.get(ch.id, 0) for ch in self.channels() if ch.topic == topic)
            times = self.topic_times(topic) if windowed else None
            if windowed and times is None:
                return None
            total += _count_window(n, times, window)
        return total

    def topic_times(self, topic: str) -> Any:
        """Sorted log times (numpy int64) of every message on ``topic`` from the log's index,
        without reading message data; None when the format or this file has no such index."""
        return None

    def index_offsets(self, topics: Iterable[str], start_ns: int) -> dict[str, int] | None:
        """Per topic, how many of its messages lie before ``start_ns``, from :meth:`topic_times`
        (None when a topic has no such index). Frame indices then count indexed messages, also
        those a damaged region makes unreadable."""
        import numpy as np

        out: dict[str, int] = {}
        for t in topics:
            times = self.topic_times(t)
            if times is None:
                return None
            out[t] = int(np.searchsorted(np.asarray(times), start_ns, side="left"))
        return out

    def stream(
        self,
        topics: Iterable[str] | None = None,
        *,
        start_ns: int | None = None,
        end_ns: int | None = None,
        stride: int = 1,
        indices: Mapping[str, Container[int]] | None = None,
        passthrough: Iterable[str] = (),
        errors: list[FrameError] | None = None,
    ) -> Iterator[StreamItem]:
        """The one frame stream every step reads: camera messages of ``topics`` (default: every
        camera topic) as :class:`StreamItem` with their frame index, in log-time order.

        A camera message is yielded when it lies in the log-time window [``start_ns``,
        ``end_ns``), its index is a multiple of ``stride`` and (``indices`` given) its index is
        in ``indices[topic]``. Messages of the ``passthrough`` topics come along unfiltered
        (``index``/``frame`` None), interleaved in log-time order. Messages that do not
        deserialize are reported (warning, ``errors``, ``report.bad_messages``).
        """
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
            raise ConfigError(f"stride must be an integer >= 1, got {stride!r}")
        cams = set(self.check_camera_topics(topics))
        extra = set(passthrough) - cams
        if not cams and not extra:
            return
        decoders: dict[int, Any] = {}
        counters: dict[str, int] = {}
        read_from = None if cams else start_ns
        if start_ns is not None and cams:
            # With an index of message times, the window's first index is known without reading
            # what comes before it; otherwise read from the start, counting.
            offsets = self.index_offsets(cams, start_ns)
            if offsets is not None:
                counters, read_from = offsets, start_ns
        for m in self.messages(cams | extra, read_from, end_ns, True):
            topic = m.channel.topic
            if topic not in cams:
                if start_ns is None or m.log_time >= start_ns:
                    yield StreamItem(m)
                continue
            idx = counters.get(topic, 0)
            counters[topic] = idx + 1
            if start_ns is not None and m.log_time < start_ns:
                continue
            if idx % stride or (indices is not None and idx not in indices.get(topic, ())):
                continue
            yield StreamItem(m, idx, self.to_frame(m, idx, decoders, errors))

    def frames(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
        stride: int = 1,
        errors: list[FrameError] | None = None,
        *,
        indices: Mapping[str, Container[int]] | None = None,
    ) -> Iterator[Frame]:
        """Camera frames of :meth:`stream` (payloads still encoded); messages that do not
        deserialize are reported and left out."""
        for item in self.stream(topics, start_ns=start_ns, end_ns=end_ns, stride=stride, indices=indices,
                                errors=errors):
            if item.frame is not None:
                yield item.frame

    def to_frame(
        self, m: RawMessage, idx: int, decoders: dict[int, Any], errors: list[FrameError] | None
    ) -> Frame | None:
        """Deserialize camera message ``m`` (the ``idx``-th of its topic) into a Frame; None if it fails
        (reported). ``decoders`` caches one deserializer per channel across calls."""
        ch = m.channel
        try:
            dec = decoders.get(ch.id)
            if dec is None:
                try:
                    dec = decoders[ch.id] = make_deserializer(ch)
                except UnsupportedEncoding as exc:
                    dec = decoders[ch.id] = exc  # parse the schema once; report every message
            if isinstance(dec, UnsupportedEncoding):
                raise dec
            msg = dec(m.data)
            stamp, frame_id, payload = extract_image(ch.msgtype, msg)
        except UnsupportedEncoding as exc:
            self._frame_error(m, idx, str(exc), errors)
            return None
        except Exception as exc:  # a corrupt message must not stop the run
            self._frame_error(m, idx, f"message does not deserialize as {ch.msgtype}: {type(exc).__name__}: {exc}", errors)
            return None
        return Frame(
            topic=ch.topic,
            index=idx,
            log_time_ns=m.log_time,
            stamp_ns=stamp if stamp is not None else m.log_time,
            frame_id=frame_id,
            payload=payload,
            msgtype=ch.msgtype,
        )

    def absorb(self, report: ReadReport, errors: Iterable[FrameError]) -> None:
        """Frame-level damage that a worker found reading this same log (its ``report`` and frame
        ``errors``): counted in this reader's report and warned as if this reader had found it."""
        self.report.bad_messages += report.bad_messages
        self.report.undecodable_frames += report.undecodable_frames
        for err in errors:
            self.warn(str(err))

    def _frame_error(self, m: RawMessage, idx: int, reason: str, errors: list[FrameError] | None) -> None:
        err = FrameError(self.path, m.channel.topic, idx, m.log_time, reason)
        self.report.bad_messages += 1
        if errors is not None:
            errors.append(err)
        self.warn(str(err))

    def decode_error(self, frame: Frame, exc: ImageDecodeError) -> FrameError:
        """Record a frame whose pixels do not decode; returns the error for the caller's list."""
        err = FrameError(self.path, frame.topic, frame.index, frame.log_time_ns, f"image does not decode: {exc}")
        self.report.undecodable_frames += 1
        self.warn(str(err))
        return err


def _count_window(n: int, times: Any, window: FrameWindow) -> int:
    """Frames of a topic with ``n`` messages (log times ``times`` when a window is set) that lie
    in the window and on the stride (indices counted from the first message)."""
    import numpy as np

    first, last = 0, n
    if times is not None:
        t = np.asarray(times)
        if window.start_ns is not None:
            first = int(np.searchsorted(t, window.start_ns, side="left"))
        if window.end_ns is not None:
            last = int(np.searchsorted(t, window.end_ns, side="left"))
    if last <= first:
        return 0
    s = window.stride
    return (last - 1) // s - (first + s - 1) // s + 1
