"""The reader interface every log format implements, and the frame stream built on it."""

from __future__ import annotations

import logging
import os
from abc import ABC, abstractmethod
from collections.abc import Callable, Container, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from types import TracebackType
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.errors import ConfigError, ImageDecodeError, TopicError
from memlog.io.camera import CAMERA_TYPES, camera_kind, extract_image
from memlog.io.decoders import UnsupportedEncoding, make_deserializer
from memlog.io.frame import Frame
from memlog.io.frame_table import FrameTable
from memlog.io.spool import ChunkSpool, spool_of
from memlog.io.records import Attachment, ChannelInfo, RawMessage, ReadReport
from memlog.io.types import ImagePayload, LogInfo, TopicInfo
from memlog.io.video import VIDEO_CODECS, VideoDecoder, codec_of, keyframe_before, payload_is_keyframe
from memlog.runtime import current

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

    For a camera message: ``index`` is its frame index (its position in the topic's
    :class:`~memlog.io.frame_table.FrameTable`: the same whatever the window, stride or reader),
    ``frame`` the deserialized frame (None when
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


_LOG = logging.getLogger("memlog.io")


def _warn_log(text: str) -> None:
    _LOG.warning(text)


def _silent(text: str) -> None:
    """The warning hook of a reader whose warnings its caller reports (a worker's)."""


class LogReader(ABC):
    """A log opened for streaming. Use :func:`memlog.io.open_log` to get one.

    Subclasses implement :meth:`channels`, :meth:`_iter_messages` (messages carry
    ``RawMessage.where``), :meth:`frame_table` and optionally :meth:`metadata` /
    :meth:`attachments`. Everything streams: no method loads the whole log.

    Warnings go to :attr:`report` and to :attr:`on_warning` (default: the ``memlog.io`` logger);
    a warning this process already said about the same file is recorded but not said again.
    """

    format: str = ""
    profile: str = ""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = os.fspath(path)
        self.report = ReadReport(self.path)
        self.on_warning: Callable[[str], None] = _warn_log
        self._said: set[str] = set()  # readers of the same file share it (memlog.io._opened)
        self._pending: list[str] = []  # what opening found that nobody has said yet (a quiet reader learned it)
        self._spool: ChunkSpool | None | bool = False  # (False: not looked up yet)

    def spool(self) -> ChunkSpool | None:
        """This log's spool while a job of it runs (:mod:`memlog.io.spool`: chunks read once per
        job); looked up once per reader."""
        if self._spool is False:
            self._spool = spool_of(self.path)
        return self._spool if isinstance(self._spool, ChunkSpool) else None

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
        """Messages per channel id from an index (or the scan made when the log was opened), or
        None when only a full read can tell."""
        return None

    @abstractmethod
    def frame_table(self, topic: str) -> FrameTable:
        """The frame numbering of camera ``topic`` (see :mod:`memlog.io.frame_table`), built once."""

    def checksums(self) -> str:
        """What the data read so far was checked against: ``"all"`` (every chunk had a CRC and
        was checked), ``"some"``, ``"none"`` (the format or file has no checksums: flipped bytes
        cannot be detected) or ``"unknown"`` (nothing read yet)."""
        return "none"

    def checksum_checks(self) -> dict[str, str]:
        """Each checksum the format has and how it fared, for formats that have several (MCAP):
        ``chunks`` ("held": every chunk read had a CRC and it matched, "some", "absent", "failed",
        "none": no chunks, "unread"), ``data_section`` (the CRC over an unchunked file's records:
        "held", "failed", "absent", "unchecked": a chunked file's chunk CRCs cover its messages)
        ``summary`` ("held", "failed", "absent", "none": no summary) and ``attachments`` (their
        CRCs: "held", "some", "absent", "failed", "none": no attachment, "unread"). Empty where
        the format has at most one kind."""
        return {}

    def close(self) -> None:
        """Release the file."""

    # -- shared ---------------------------------------------------------------------
    def __enter__(self) -> "LogReader":
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    def warn(self, text: str) -> None:
        self.report.warn(text)
        if self.on_warning is _silent or text in self._said:
            return
        self._said.add(text)
        self.on_warning(text)

    def quiet_warnings(self) -> None:
        """Record warnings in :attr:`report` only (a worker's reader: its caller reports them)."""
        self.on_warning = _silent

    def _learned_before(self, report: ReadReport) -> None:
        """Start from what an earlier reader of this file found when it opened it (``report``):
        recorded here; warnings nobody said yet are said at the first read."""
        self.report.merge(report)
        self._pending = [w for w in report.warnings if w not in self._said]

    def _say_pending(self) -> None:
        pending, self._pending = self._pending, []
        for text in pending:
            self.warn(text)

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
        self._say_pending()
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
        self._say_pending()
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

    def _widen_topic_ranges(self, info: LogInfo, ranges: Mapping[int, Sequence[int]]) -> None:
        """Widen each topic's time range in ``info`` by ``ranges`` (channel id -> ``[start, end]`` ns)
        of its channels."""
        channels = [c for c in self.channels() if c.id in ranges]
        for t in info.topics:
            for c in channels:
                if c.topic == t.topic:
                    lo, hi = ranges[c.id]
                    t.start_ns = lo if t.start_ns is None else min(t.start_ns, lo)
                    t.end_ns = hi if t.end_ns is None else max(t.end_ns, hi)

    def check_camera_topics(self, topics: Iterable[str] | None) -> list[str]:
        """The camera topics to stream: ``topics`` (checked: each must be a camera topic of
        this log) or, when None, every camera topic (an undamaged log without one is a usage error
        that lists its topics and types). :class:`TopicError` names what is wrong."""
        cams = self.camera_topics()
        if topics is None:
            if not cams and self.report.ok:  # (a damaged log may have lost its camera channels: damage, not usage)
                seen = ", ".join(f"{c.topic} ({c.msgtype})" for c in sorted(self.channels(), key=lambda c: c.topic))
                raise TopicError(f"{self.path}: no camera topic memlog can read (topics: {seen or 'none'}); memlog "
                                 f"reads {', '.join(CAMERA_TYPES)}")
            return cams
        wanted = sorted(set(topics))
        not_cam = set(wanted) - set(cams)
        if not_cam:
            bad = ", ".join(sorted(not_cam))
            if not_cam - set(self.topics()):
                raise TopicError(f"{self.path}: no topic {bad} (camera topics: {', '.join(cams) or 'none'})")
            raise TopicError(f"{self.path}: topic {bad} is not a camera topic (camera topics: {', '.join(cams) or 'none'})")
        return wanted

    def count_frames(self, window: FrameWindow) -> int:
        """How many frames :meth:`stream` yields for ``window`` at most (from the frame tables;
        frames listed by the index but unreadable are counted)."""
        total = 0
        for topic in self.check_camera_topics(window.topics):
            first, last = self.frame_table(topic).window(window.start_ns, window.end_ns)
            total += _on_stride(first, last, window.stride)
        return total

    def topic_times(self, topic: str) -> Any:
        """Sorted log times (numpy int64) of the frames of camera ``topic`` (its
        :meth:`frame_table`: position = frame index), without reading message data when the log
        has a trusted index."""
        return self.frame_table(topic).times

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
        tables = {t: self.frame_table(t) for t in cams}
        # a video topic is decoded from the keyframe at or before the first frame wanted
        video_from = {t: self._video_start(t, tables[t], start_ns, end_ns, stride, indices)
                      for t in cams if self._is_video(t)}
        read_from = start_ns
        if start_ns is not None and video_from:
            read_from = min([start_ns] + [int(tables[t].times[i]) for t, i in video_from.items() if i is not None])
        decoders: dict[int, Any] = {}
        videos: dict[str, VideoDecoder] = {}
        for m in self.messages(cams | extra, read_from, end_ns, True):
            topic = m.channel.topic
            early = start_ns is not None and m.log_time < start_ns  # read only for a video's keyframe
            if topic not in cams:
                if not early:
                    yield StreamItem(m)
                continue
            idx = tables[topic].index_of(m.where)
            if idx < 0:
                self.report.index_damaged = True
                if self.report.count("bad_messages", ("unlisted", m.where, topic)):
                    self.warn(f"{self.path}: topic {topic}: a message at log time {m.log_time} is not in the log's "
                              "index, so it has no frame index (the index is damaged); skipped")
                continue
            wanted = not early and not idx % stride and (indices is None or idx in indices.get(topic, ()))
            if topic in video_from:
                first = video_from[topic]
                if first is None or idx < first:
                    continue
                frame = self._video_frame(m, idx, wanted, decoders, videos, errors)
                if wanted:
                    yield StreamItem(m, idx, frame)
                continue
            if wanted:
                yield StreamItem(m, idx, self.to_frame(m, idx, decoders, errors))

    def _is_video(self, topic: str) -> bool:
        return any(c.topic == topic and camera_kind(c.msgtype) == "video" for c in self.channels())

    def _video_start(self, topic: str, table: FrameTable, start_ns: int | None, end_ns: int | None, stride: int,
                     indices: Mapping[str, Container[int]] | None) -> int | None:
        """The frame index video ``topic`` is decoded from: the keyframe at or before the first
        frame :meth:`stream` yields (None: it yields none)."""
        first, last = table.window(start_ns, end_ns)
        if indices is not None:
            mine = indices.get(topic, ())
            wanted = [i for i in (mine if isinstance(mine, Iterable) else range(first, last))
                      if first <= i < last and not i % stride and i in mine]
            if not wanted:
                return None
            lo = min(wanted)
        else:
            lo = first + (-first) % stride
            if lo >= last:
                return None
        return 0 if lo == 0 else keyframe_before(self.video_keyframes(topic), lo)

    def video_keyframes(self, topic: str) -> npt.NDArray[np.int64]:
        """The frame indices of video ``topic``'s keyframes (found in the packets once per log and
        process, kept in the runtime context: :mod:`memlog.io.video`)."""
        from memlog.io._opened import file_key

        def scan() -> npt.NDArray[np.int64]:
            table = self.frame_table(topic)
            found: list[int] = []
            decoders: dict[int, Any] = {}
            for m in self.messages({topic}, None, None, True):
                idx = table.index_of(m.where)
                if idx < 0:
                    continue
                try:
                    _stamp, _fid, payload = extract_image(m.channel.msgtype, self._deserializer(m, decoders)(m.data))
                except Exception:  # a packet that does not deserialize is reported where it is streamed
                    continue
                codec = codec_of(payload.encoding)
                if codec is not None and payload_is_keyframe(codec, payload):
                    found.append(idx)
            return np.asarray(sorted(found), dtype=np.int64)

        key = ("video-keyframes", file_key("video", self.path), topic)
        return current().indexes.get(key, scan)

    def _video_frame(self, m: RawMessage, idx: int, wanted: bool, decoders: dict[int, Any],
                     videos: dict[str, VideoDecoder], errors: list[FrameError] | None) -> Frame | None:
        """Feed video message ``m`` to its topic's decoder; the frame with its decoded pixels when
        ``wanted`` (None, reported, when it cannot be shown)."""
        topic = m.channel.topic
        frame = self.to_frame(m, idx, decoders, errors if wanted else None, report=wanted)
        dec = videos.get(topic)
        if frame is None:
            if dec is not None:
                dec.synced = False  # a lost packet: the frames after it wait for a keyframe
            return None
        codec = codec_of(frame.payload.encoding)
        if codec is None:
            if wanted:
                self._frame_error(m, idx, f"video format {frame.payload.encoding!r} is not one memlog decodes "
                                          f"({', '.join(VIDEO_CODECS)})", errors)
            return None
        if dec is None or dec.codec != codec:
            dec = videos[topic] = VideoDecoder(codec, topic)
        key = payload_is_keyframe(codec, frame.payload)
        try:
            bgr = dec.decode(frame.payload.data, key, wanted)
        except ImageDecodeError as exc:
            if wanted:
                err = self.decode_error(frame, exc)
                if errors is not None:
                    errors.append(err)
            return None
        if bgr is None:
            return None
        h, w = bgr.shape[:2]
        return replace(frame, payload=ImagePayload("raw", "bgr8", bgr.tobytes(), width=w, height=h, step=3 * w))

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
        self, m: RawMessage, idx: int, decoders: dict[int, Any], errors: list[FrameError] | None, *,
        report: bool = True,
    ) -> Frame | None:
        """Deserialize camera message ``m`` (the ``idx``-th of its topic) into a Frame; None if it fails
        (reported, unless ``report`` is false). ``decoders`` caches one deserializer per channel."""
        ch = m.channel
        try:
            msg = self._deserializer(m, decoders)(m.data)
            stamp, frame_id, payload = extract_image(ch.msgtype, msg)
        except UnsupportedEncoding as exc:
            if report:
                self._frame_error(m, idx, str(exc), errors)
            return None
        except Exception as exc:  # a corrupt message must not stop the run
            if report:
                self._frame_error(m, idx, f"message does not deserialize as {ch.msgtype}: {type(exc).__name__}: "
                                          f"{exc}", errors)
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

    @staticmethod
    def _deserializer(m: RawMessage, decoders: dict[int, Any]) -> Any:
        """The deserializer of ``m``'s channel (made once; :class:`UnsupportedEncoding` when there is none)."""
        dec = decoders.get(m.channel.id)
        if dec is None:
            try:
                dec = decoders[m.channel.id] = make_deserializer(m.channel)
            except UnsupportedEncoding as exc:
                dec = decoders[m.channel.id] = exc  # parse the schema once; report every message
        if isinstance(dec, UnsupportedEncoding):
            raise dec
        return dec

    def absorb(self, report: ReadReport, errors: Iterable[FrameError] = ()) -> None:
        """The damage a worker found reading this same log (its ``report`` and frame ``errors``):
        added to this reader's report (damage at the same place counts once) and warned, once, as
        if this reader had found it."""
        before = set(self.report.warnings)
        self.report.merge(report)
        for text in report.warnings:
            if text not in before:
                self.warn(text)
        for err in errors:
            self.warn(str(err))

    def _frame_error(self, m: RawMessage, idx: int, reason: str, errors: list[FrameError] | None) -> None:
        err = FrameError(self.path, m.channel.topic, idx, m.log_time, reason)
        self.report.count("bad_messages", ("frame", m.channel.topic, idx))
        if errors is not None:
            errors.append(err)
        self.warn(str(err))

    def decode_error(self, frame: Frame, exc: ImageDecodeError) -> FrameError:
        """Record a frame whose pixels do not decode; returns the error for the caller's list."""
        err = FrameError(self.path, frame.topic, frame.index, frame.log_time_ns, f"image does not decode: {exc}")
        self.report.count("undecodable_frames", (frame.topic, frame.index))
        self.warn(str(err))
        return err


def _on_stride(first: int, last: int, stride: int) -> int:
    """How many multiples of ``stride`` lie in [``first``, ``last``)."""
    if last <= first:
        return 0
    return (last - 1) // stride - (first + stride - 1) // stride + 1
