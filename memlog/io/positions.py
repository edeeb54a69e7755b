"""Positions of the platform from a log (NavSatFix, Foxglove LocationFix, poses, odometry),
interpolated to frame times, in local metres; and the log's own motion (:func:`read_motion`:
odometry, poses, twists, GNSS), which decides where the drive stood still
(:mod:`memlog.scoring.motion`).

GNSS fixes are projected to a local east/north frame around the first fix
(equirectangular: accurate to centimetres over the few kilometres of a drive); poses and
odometry are used as they are (x, y, z in their frame).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.errors import TopicError
from memlog.io.base import LogReader
from memlog.io.camera import normalize_msgtype
from memlog.io.decoders import make_deserializer

__all__ = ["PositionTrack", "position_topics", "read_track", "EARTH_RADIUS_M", "geo_origin", "geo_to_local", "local_to_geo",
           "MotionTrack", "MOTION_KINDS", "motion_topics", "read_motion", "read_tracks", "interpolate"]

EARTH_RADIUS_M = 6_371_008.8
_GNSS = {"sensor_msgs/NavSatFix", "foxglove.LocationFix", "foxglove_msgs/LocationFix"}
_POSE = {
    "geometry_msgs/PoseStamped", "geometry_msgs/PoseWithCovarianceStamped", "nav_msgs/Odometry",
    "geometry_msgs/TransformStamped", "foxglove.PoseInFrame", "foxglove_msgs/PoseInFrame",
}
#: Measured velocities (wheel speed, a GNSS receiver's velocity: nmea_navsat_driver ``vel``, ublox
#: ``fix_velocity``). A plain ``geometry_msgs/Twist`` is left out: it is what ``cmd_vel`` carries,
#: a command, not what the vehicle did.
_TWIST = {"geometry_msgs/TwistStamped", "geometry_msgs/TwistWithCovarianceStamped"}


def interpolate(t_ns: npt.ArrayLike, values: npt.ArrayLike, at_ns: Iterable[int],
                max_gap_s: float) -> npt.NDArray[np.float64]:
    """``values`` (one row per sample at ``t_ns``, increasing; [M] or [M, k]) linearly
    interpolated at ``at_ns``: held at the ends within ``max_gap_s`` of the first/last sample,
    NaN further out and inside a gap between samples longer than ``max_gap_s``."""
    ts = np.asarray(t_ns, dtype=np.int64)
    v = np.asarray(values, dtype=np.float64)
    flat = v.ndim == 1
    v2 = v.reshape(len(v), -1)
    t = np.asarray(list(at_ns), dtype=np.int64)
    out = np.full((len(t), v2.shape[1]), np.nan)
    if len(ts) == 1:
        out[np.abs(t - ts[0]) <= max_gap_s * 1e9] = v2[0]
    elif len(ts) > 1:
        tt = (ts - ts[0]).astype(np.float64)
        q = (t - ts[0]).astype(np.float64)
        for k in range(v2.shape[1]):
            out[:, k] = np.interp(q, tt, v2[:, k])  # ends held within max_gap_s, NaN beyond
        out[(q < -max_gap_s * 1e9) | (q > tt[-1] + max_gap_s * 1e9)] = np.nan
        # neighbours too far apart in time: unknown
        j = np.clip(np.searchsorted(tt, q), 1, len(tt) - 1)
        out[(tt[j] - tt[j - 1]) > max_gap_s * 1e9] = np.nan
    return out[:, 0] if flat else out


def geo_origin(latlon: npt.ArrayLike) -> tuple[float, float]:
    """Origin of a local frame for geographic points: mean latitude and circular mean longitude
    of the finite rows of ``latlon`` ([N, >=2] degrees); (0, 0) when there is none."""
    a = np.asarray(latlon, dtype=np.float64)
    fin = a[np.all(np.isfinite(a[:, :2]), axis=1), :2] if a.ndim == 2 and a.size else np.zeros((0, 2))
    if not fin.size:
        return 0.0, 0.0
    lon = np.radians(fin[:, 1])
    return float(fin[:, 0].mean()), float(np.degrees(np.arctan2(np.sin(lon).mean(), np.cos(lon).mean())))


def geo_to_local(latlon: npt.ArrayLike, origin: tuple[float, float]) -> npt.NDArray[np.float64]:
    """Equirectangular projection of (lat, lon) degrees to local (east, north) metres about
    ``origin``; longitudes are wrapped across the antimeridian (+-180). Accurate to centimetres
    over the few kilometres of a drive, well under 1 % over tens of km."""
    a = np.asarray(latlon, dtype=np.float64)
    lat0, lon0 = origin
    dlon = (a[:, 1] - lon0 + 180.0) % 360.0 - 180.0
    x = EARTH_RADIUS_M * np.radians(dlon) * math.cos(math.radians(lat0))
    y = EARTH_RADIUS_M * np.radians(a[:, 0] - lat0)
    return np.stack([x, y], axis=1)


def local_to_geo(xy: npt.ArrayLike, origin: tuple[float, float]) -> npt.NDArray[np.float64]:
    """Inverse of :func:`geo_to_local`: (lat, lon) degrees, longitude wrapped into [-180, 180)."""
    a = np.asarray(xy, dtype=np.float64)
    lat0, lon0 = origin
    lat = lat0 + np.degrees(a[:, 1] / EARTH_RADIUS_M)
    lon = (lon0 + np.degrees(a[:, 0] / (EARTH_RADIUS_M * math.cos(math.radians(lat0)))) + 180.0) % 360.0 - 180.0
    return np.stack([lat, lon], axis=1)


@dataclass
class PositionTrack:
    """Timestamps (ns) and positions: ``xyz`` in metres (local frame); ``latlon`` for GNSS tracks."""

    topic: str
    kind: str  # "gnss" or "pose"
    t_ns: npt.NDArray[np.int64]
    xyz: npt.NDArray[np.float64]
    latlon: npt.NDArray[np.float64] | None = None

    def at(self, t_ns: Iterable[int], max_gap_s: float = 5.0) -> npt.NDArray[np.float64]:
        """Positions linearly interpolated at ``t_ns``; NaN further than ``max_gap_s`` outside the
        track or inside a gap between fixes longer than ``max_gap_s``."""
        return interpolate(self.t_ns, self.xyz, t_ns, max_gap_s)

    def latlon_at(self, t_ns: Iterable[int]) -> npt.NDArray[np.float64] | None:
        if self.latlon is None:
            return None
        xyz = self.at(t_ns)
        ll = local_to_geo(xyz[:, :2], (float(self.latlon[0, 0]), float(self.latlon[0, 1])))
        return np.stack([ll[:, 0], ll[:, 1], xyz[:, 2]], axis=1)


def position_topics(reader: LogReader) -> list[tuple[str, str]]:
    """(topic, "gnss"|"pose") for every topic that carries positions, GNSS first."""
    out = []
    for c in reader.channels():
        t = normalize_msgtype(c.msgtype)
        if t in _GNSS:
            out.append((c.topic, "gnss"))
        elif t in _POSE:
            out.append((c.topic, "pose"))
    return sorted(set(out), key=lambda x: (x[1] != "gnss", x[0]))


def _g(m: Any, name: str) -> Any:
    return m.get(name) if isinstance(m, dict) else getattr(m, name, None)


def _xyz(msgtype: str, m: Any) -> tuple[float, float, float] | None:
    t = normalize_msgtype(msgtype)
    if t in _GNSS:
        lat, lon, alt = _g(m, "latitude"), _g(m, "longitude"), _g(m, "altitude")
        status = _g(m, "status")
        if status is not None and _g(status, "status") is not None and int(_g(status, "status")) < 0:
            return None  # NO_FIX
        if lat is None or lon is None or not (math.isfinite(lat) and math.isfinite(lon)):
            return None
        return float(lat), float(lon), float(alt or 0.0)
    if t == "nav_msgs/Odometry" or t == "geometry_msgs/PoseWithCovarianceStamped":
        p = _g(_g(_g(m, "pose"), "pose"), "position")
    elif t == "geometry_msgs/TransformStamped":
        p = _g(_g(m, "transform"), "translation")
    else:
        p = _g(_g(m, "pose"), "position")
    if p is None:
        return None
    return float(_g(p, "x")), float(_g(p, "y")), float(_g(p, "z") or 0.0)


def _position_topic(reader: LogReader, topic: str | None) -> tuple[str, str] | None:
    """(topic, kind) of the positions to read: ``topic`` (which must carry positions), else the
    first GNSS, else pose topic; None when the log has none."""
    topics = position_topics(reader)
    if topic is None:
        return topics[0] if topics else None
    kinds = dict(topics)
    if topic not in kinds:
        raise TopicError(f"--position-topic: {reader.path}: topic {topic} carries no positions (NavSatFix, pose or odometry)")
    return topic, kinds[topic]


def read_track(reader: LogReader, topic: str | None = None) -> PositionTrack | None:
    """The position track of ``topic`` (default: the first GNSS, else pose topic), or None."""
    chosen = _position_topic(reader, topic)
    if chosen is None:
        return None
    return _position_track(*chosen, _samples(reader, [chosen[0]])[chosen[0]])


def read_tracks(reader: LogReader, position_topic: str | None = None) -> tuple[PositionTrack | None, list[MotionTrack]]:
    """:func:`read_track` of ``position_topic`` and :func:`read_motion`, in one pass over the log."""
    chosen = _position_topic(reader, position_topic)
    topics = motion_topics(reader)
    samples = _samples(reader, [t for t, _ in topics])
    track = None if chosen is None else _position_track(*chosen, samples[chosen[0]])
    return track, _motion_tracks(topics, samples)


def read_motion(reader: LogReader) -> list[MotionTrack]:
    """The motion of every topic that carries some (:func:`motion_topics`, in that order; one pass
    over them), each with at least one sample; [] when the log has none."""
    topics = motion_topics(reader)
    return _motion_tracks(topics, _samples(reader, [t for t, _ in topics]))


class _Samples:
    """What a topic's messages said: log times, positions (GNSS: lat, lon, alt) and speeds, one
    entry per message that gave what its kind gives (a position; a twist: a speed)."""

    def __init__(self) -> None:
        self.t: list[int] = []
        self.xyz: list[tuple[float, float, float]] = []
        self.speed: list[float] = []


def _samples(reader: LogReader, topics: list[str]) -> dict[str, _Samples]:
    """:class:`_Samples` of each of ``topics`` (position, odometry, twist topics), one pass."""
    out = {t: _Samples() for t in topics}
    if not topics:
        return out
    decoders: dict[int, Any] = {}
    for msg in reader.messages(topics):
        try:
            dec = decoders.get(msg.channel.id) or decoders.setdefault(msg.channel.id, make_deserializer(msg.channel))
            xyz, speed = _motion_of(msg.channel.msgtype, dec(msg.data))
        except Exception as exc:  # a bad fix is skipped like a bad frame
            reader.warn(f"{reader.path}: topic {msg.channel.topic} message at log time {msg.log_time} does not "
                        f"decode: {exc}")
            continue
        if xyz is None and speed is None:
            continue
        if xyz is None and normalize_msgtype(msg.channel.msgtype) not in _TWIST:
            continue  # a pose, odometry or fix without a position (GNSS: no fix)
        got = out[msg.channel.topic]
        got.t.append(msg.log_time)
        if xyz is not None:
            got.xyz.append(xyz)
        got.speed.append(math.nan if speed is None else speed)
    return out


def _gnss_local(latlonalt: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """(lat, lon, alt) fixes as local (east, north, alt) metres about the first fix."""
    xy = geo_to_local(latlonalt, (float(latlonalt[0, 0]), float(latlonalt[0, 1])))
    return np.column_stack([xy, latlonalt[:, 2]])


def _position_track(topic: str, kind: str, got: _Samples) -> PositionTrack:
    t = np.asarray(got.t, dtype=np.int64)
    a = np.asarray(got.xyz, dtype=np.float64).reshape(-1, 3)
    if kind == "gnss":
        return PositionTrack(topic, kind, t, _gnss_local(a) if len(a) else a, a)
    return PositionTrack(topic, kind, t, a)


#: The kinds of motion a log may carry, in the order they are preferred for finding stops:
#: odometry (``nav_msgs/Odometry``: its pose, or its twist when the pose is not filled in), other
#: poses, measured velocities (twists), GNSS fixes (whose positions wander the most while standing).
MOTION_KINDS = ("odometry", "pose", "twist", "gnss")


@dataclass
class MotionTrack:
    """What one topic says about the platform's motion: sample times (log time, ns), positions
    ``xyz`` ([M, 3] metres in a local frame; GNSS: east, north and 0, a fix's altitude wanders the
    most) and/or ``speed`` ([M] m/s, the norm of the linear velocity, NaN where a message had none);
    None where the kind has none (a twist has no positions, a pose or a fix no speed)."""

    topic: str
    kind: str  # one of MOTION_KINDS
    t_ns: npt.NDArray[np.int64]
    xyz: npt.NDArray[np.float64] | None = None
    speed: npt.NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.t_ns)

    def at(self, t_ns: Iterable[int], max_gap_s: float) -> tuple[npt.NDArray[np.float64] | None,
                                                                  npt.NDArray[np.float64] | None]:
        """Positions and speeds at ``t_ns`` (:func:`interpolate`; NaN where unknown)."""
        t = list(t_ns)
        return (None if self.xyz is None else interpolate(self.t_ns, self.xyz, t, max_gap_s),
                None if self.speed is None else interpolate(self.t_ns, self.speed, t, max_gap_s))


def motion_topics(reader: LogReader) -> list[tuple[str, str]]:
    """(topic, kind) of every topic that says how the platform moved, in :data:`MOTION_KINDS` order
    (then by topic)."""
    out = set()
    for c in reader.channels():
        t = normalize_msgtype(c.msgtype)
        kind = ("odometry" if t == "nav_msgs/Odometry" else "pose" if t in _POSE else "twist" if t in _TWIST
                else "gnss" if t in _GNSS else None)
        if kind is not None:
            out.add((c.topic, kind))
    return sorted(out, key=lambda x: (MOTION_KINDS.index(x[1]), x[0]))


def _linear_speed(msgtype: str, m: Any) -> float | None:
    """The norm of a twist's linear velocity (m/s); None when the message has none."""
    twist = _g(m, "twist")
    if normalize_msgtype(msgtype) in ("nav_msgs/Odometry", "geometry_msgs/TwistWithCovarianceStamped"):
        twist = _g(twist, "twist")
    lin = _g(twist, "linear")
    if lin is None:
        return None
    v = math.sqrt(sum(float(_g(lin, k) or 0.0) ** 2 for k in ("x", "y", "z")))
    return v if math.isfinite(v) else None


def _motion_of(msgtype: str, m: Any) -> tuple[tuple[float, float, float] | None, float | None]:
    """A message's position (odometry, poses, GNSS: :func:`_xyz`) and speed (odometry, twists)."""
    t = normalize_msgtype(msgtype)
    if t in _TWIST:
        return None, _linear_speed(msgtype, m)
    return _xyz(msgtype, m), (_linear_speed(msgtype, m) if t == "nav_msgs/Odometry" else None)


def _motion_tracks(topics: list[tuple[str, str]], samples: dict[str, _Samples]) -> list[MotionTrack]:
    out = []
    for topic, kind in topics:
        got = samples[topic]
        if not got.t:
            continue
        xyz = None
        if kind != "twist":
            xyz = np.asarray(got.xyz, dtype=np.float64).reshape(-1, 3)
            if kind == "gnss":
                xyz = _gnss_local(xyz) * np.array([1.0, 1.0, 0.0])
        speed = np.asarray(got.speed, dtype=np.float64) if kind in ("odometry", "twist") else None
        out.append(MotionTrack(topic, kind, np.asarray(got.t, dtype=np.int64), xyz, speed))
    return out
