"""Positions of the platform from a log (NavSatFix, Foxglove LocationFix, poses, odometry),
interpolated to frame times, in local metres.

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

__all__ = ["PositionTrack", "position_topics", "read_track", "EARTH_RADIUS_M", "geo_origin", "geo_to_local", "local_to_geo"]

EARTH_RADIUS_M = 6_371_008.8
_GNSS = {"sensor_msgs/NavSatFix", "foxglove.LocationFix", "foxglove_msgs/LocationFix"}
_POSE = {
    "geometry_msgs/PoseStamped", "geometry_msgs/PoseWithCovarianceStamped", "nav_msgs/Odometry",
    "geometry_msgs/TransformStamped", "foxglove.PoseInFrame", "foxglove_msgs/PoseInFrame",
}


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
        t = np.asarray(list(t_ns), dtype=np.int64)
        out = np.full((len(t), 3), np.nan)
        if len(self.t_ns) == 0:
            return out
        if len(self.t_ns) == 1:
            ok = np.abs(t - self.t_ns[0]) <= max_gap_s * 1e9
            out[ok] = self.xyz[0]
            return out
        tt = (self.t_ns - self.t_ns[0]).astype(np.float64)
        q = (t - self.t_ns[0]).astype(np.float64)
        for k in range(3):
            out[:, k] = np.interp(q, tt, self.xyz[:, k])  # ends held within max_gap_s, NaN beyond
        out[(q < -max_gap_s * 1e9) | (q > tt[-1] + max_gap_s * 1e9)] = np.nan
        # neighbours too far apart in time: unknown
        j = np.clip(np.searchsorted(tt, q), 1, len(tt) - 1)
        gap = (tt[j] - tt[j - 1]) > max_gap_s * 1e9
        out[gap] = np.nan
        return out

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


def read_track(reader: LogReader, topic: str | None = None) -> PositionTrack | None:
    """The position track of ``topic`` (default: the first GNSS, else pose topic), or None."""
    topics = position_topics(reader)
    if topic is None:
        if not topics:
            return None
        topic, kind = topics[0]
    else:
        kinds = dict(topics)
        if topic not in kinds:
            raise TopicError(f"--position-topic: {reader.path}: topic {topic} carries no positions (NavSatFix, pose or odometry)")
        kind = kinds[topic]
    decoders: dict[int, Any] = {}
    ts: list[int] = []
    vals: list[tuple[float, float, float]] = []
    for msg in reader.messages([topic]):
        try:
            dec = decoders.get(msg.channel.id) or decoders.setdefault(msg.channel.id, make_deserializer(msg.channel))
            v = _xyz(msg.channel.msgtype, dec(msg.data))
        except Exception as exc:  # a bad fix is skipped like a bad frame
            reader.warn(f"{reader.path}: topic {topic} message at log time {msg.log_time} does not decode: {exc}")
            continue
        if v is not None:
            ts.append(msg.log_time)
            vals.append(v)
    t = np.asarray(ts, dtype=np.int64)
    a = np.asarray(vals, dtype=np.float64).reshape(-1, 3)
    if kind == "gnss":
        if len(a) == 0:
            return PositionTrack(topic, kind, t, a, a)
        xy = geo_to_local(a, (float(a[0, 0]), float(a[0, 1])))
        return PositionTrack(topic, kind, t, np.column_stack([xy, a[:, 2]]), a)
    return PositionTrack(topic, kind, t, a)
