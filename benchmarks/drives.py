#!/usr/bin/env python3
"""Drive variants of the shared Nordland slice: fast stretches, stops, other frame rates, mixtures.

The source drives are ``nordland_dev_summer.mcap`` (the reference) and ``nordland_dev_winter.mcap``
(the query): 800 places, frame ``i`` of both shows place ``i``, 64x32 PNG frames, 10 Hz synthetic
stamps. A *variant* is a list of source places, one per output frame, with a stamp and a flag
"add sensor noise" per frame:

==================  ==============================================================================
``base``            every place once, 10 Hz (the source drive)
``fast``            places 150-349 every 2nd (2x speed) and 500-649 every 3rd (3x), 10 Hz
``stops``           three stops of 30 frames (places 120, 400, 700 repeated with sensor noise), 10 Hz
``half-rate``       every 2nd place, 5 Hz (the same vehicle speed, half the frame rate)
``double-rate``     every place twice (the repeat with sensor noise), 20 Hz
``mixed``           a stop of 30 frames at 100, places 200-399 every 2nd, 450-549 each twice (half
                    speed), 600-749 every 3rd, a stop of 30 frames at 780, 10 Hz
``recorded``        like a recorded drive: standing 60 frames at the start and the end, stops of
                    60 and 40 frames, crawls at a third of the speed, stretches at 2x and 3x, 10 Hz
==================  ==============================================================================

Sensor noise: Gaussian, sigma 2 grey levels (of 255), on the decoded frame, re-encoded as PNG
(a standing camera's frames differ by a little noise, never by nothing). Frames keep the source
message type and schema (``sensor_msgs/msg/CompressedImage``, CDR); header stamps and log times
are the variant's. ``positions=True`` adds a ``/odom`` topic (``nav_msgs/msg/Odometry``, 10 Hz
of the variant's own clock, one message per frame) with a synthetic along-track position:
place ``p`` lies ``8 p`` metres along a gentle curve, with 5 cm noise per message.

Ground truth is recomputed by source place: ``matches[q]`` lists the reference frames whose place
is within ``tolerance`` (default 1, as the shared truth) of query frame ``q``'s place. The truth
JSON also holds both variants' place lists (``query_places``, ``reference_places``) so a user can
recompute anything from them.

As a module::

    from benchmarks.drives import VARIANTS, variant, write_variant, truth
    v = variant("stops")                      # a Variant: places, stamps_ns, noisy
    write_variant(SHARED / "nordland_dev_winter.mcap", v, "/tmp/winter-stops.mcap", positions=True)
    t = truth(v, variant("base"))             # {"matches": [...], ...}
    with_odometry(SHARED / "stromovka_drive_autumn.mcap", places, "/tmp/autumn-odom.mcap")  # any log + its places

From the command line::

    python benchmarks/drives.py --out /tmp/drives                   # every variant of both drives
    python benchmarks/drives.py --out /tmp/drives --variants stops fast --drives winter --positions
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))
DRIVES = {"summer": "nordland_dev_summer.mcap", "winter": "nordland_dev_winter.mcap"}
TOPIC = "/camera/image_raw/compressed"
ODOM_TOPIC = "/odom"
N_PLACES = 800
HZ = 10.0
NOISE_SIGMA = 2.0  # grey levels
METRES_PER_PLACE = 8.0
ODOM_NOISE_M = 0.05

__all__ = ["Variant", "VARIANTS", "variant", "write_variant", "truth", "write_truth", "source_places",
           "along_track_xy", "N_PLACES"]


@dataclass(frozen=True)
class Variant:
    """A drive variant: output frame ``j`` shows source place ``places[j]`` at ``stamps_ns[j]``
    (relative to the drive's start), with sensor noise added when ``noisy[j]``."""

    name: str
    places: npt.NDArray[np.int64]
    stamps_ns: npt.NDArray[np.int64]
    noisy: npt.NDArray[np.bool_]
    description: str

    def __post_init__(self) -> None:
        n = len(self.places)
        if len(self.stamps_ns) != n or len(self.noisy) != n:
            raise ValueError("places, stamps_ns and noisy must have one value per frame")
        if n and np.any(np.diff(self.stamps_ns) <= 0):
            raise ValueError("stamps must increase")

    def __len__(self) -> int:
        return len(self.places)


def _at_rate(name: str, places: Sequence[int], noisy: Sequence[bool], hz: float, description: str) -> Variant:
    p = np.asarray(places, dtype=np.int64)
    return Variant(name, p, np.round(np.arange(len(p)) * 1e9 / hz).astype(np.int64), np.asarray(noisy, dtype=bool),
                   description)


def _segments(parts: Sequence[tuple[str, int, int, int]], n: int) -> tuple[list[int], list[bool]]:
    """Places and noise flags from (kind, a, b, step) parts covering ``0..n-1`` in order:
    ``walk`` places a..b-1 every ``step``-th; ``stop`` place a repeated ``step`` times with noise
    (after its first showing); ``twice`` places a..b-1 each shown twice (the repeat noisy)."""
    places: list[int] = []
    noisy: list[bool] = []
    for kind, a, b, step in parts:
        if kind == "walk":
            r = list(range(a, min(b, n), step))
            places += r
            noisy += [False] * len(r)
        elif kind == "stop":
            places += [a] * step
            noisy += [True] * step
        elif kind == "twice":
            for p in range(a, min(b, n)):
                places += [p, p]
                noisy += [False, True]
        elif kind == "slow":  # each place ``step`` times: a crawl at 1/step of the speed
            for p in range(a, min(b, n)):
                places += [p] * step
                noisy += [False] + [True] * (step - 1)
        else:
            raise ValueError(kind)
    return places, noisy


def _base(n: int) -> Variant:
    return _at_rate("base", range(n), [False] * n, HZ, "every place once, 10 Hz")


def _fast(n: int) -> Variant:
    p, z = _segments([("walk", 0, 150, 1), ("walk", 150, 350, 2), ("walk", 350, 500, 1), ("walk", 500, 650, 3),
                      ("walk", 650, n, 1)], n)
    return _at_rate("fast", p, z, HZ, "places 150-349 every 2nd, 500-649 every 3rd, 10 Hz")


def _stops(n: int) -> Variant:
    parts: list[tuple[str, int, int, int]] = []
    a = 0
    for s in (120, 400, 700):
        if s >= n:
            break
        parts += [("walk", a, s + 1, 1), ("stop", s, 0, 30)]
        a = s + 1
    parts.append(("walk", a, n, 1))
    p, z = _segments(parts, n)
    return _at_rate("stops", p, z, HZ, "stops of 30 frames at places 120, 400, 700 (sensor noise), 10 Hz")


def _half_rate(n: int) -> Variant:
    return _at_rate("half-rate", range(0, n, 2), [False] * len(range(0, n, 2)), HZ / 2, "every 2nd place, 5 Hz")


def _double_rate(n: int) -> Variant:
    p, z = _segments([("twice", 0, n, 1)], n)
    return _at_rate("double-rate", p, z, HZ * 2, "every place twice (the repeat noisy), 20 Hz")


def _mixed(n: int) -> Variant:
    p, z = _segments([("walk", 0, 101, 1), ("stop", 100, 0, 30), ("walk", 101, 200, 1), ("walk", 200, 400, 2),
                      ("walk", 400, 450, 1), ("twice", 450, 550, 1), ("walk", 550, 600, 1), ("walk", 600, 750, 3),
                      ("walk", 750, 781, 1), ("stop", 780, 0, 30), ("walk", 781, n, 1)], n)
    return _at_rate("mixed", p, z, HZ, "stop 30 at 100, 200-399 every 2nd, 450-549 twice, 600-749 every 3rd, "
                                       "stop 30 at 780, 10 Hz")


def _recorded(n: int) -> Variant:
    p, z = _segments([("stop", 0, 0, 60), ("walk", 1, 120, 1), ("slow", 120, 180, 3), ("stop", 179, 0, 60),
                      ("walk", 180, 300, 2), ("walk", 300, 421, 1), ("stop", 420, 0, 40), ("walk", 421, 600, 3),
                      ("slow", 600, 650, 3), ("walk", 650, n, 1), ("stop", n - 1, 0, 60)], n)
    return _at_rate("recorded", p, z, HZ, "like a recorded drive: standing 60 frames at the start and the end, "
                                          "a stop of 60 at 179 and 40 at 420, crawls at 1/3 speed (120-179, "
                                          "600-649), fast stretches (180-299 every 2nd, 421-599 every 3rd), 10 Hz")


#: The variants by name (each a function of the number of source places).
VARIANTS: dict[str, Callable[[int], Variant]] = {
    "base": _base, "fast": _fast, "stops": _stops, "half-rate": _half_rate, "double-rate": _double_rate,
    "mixed": _mixed, "recorded": _recorded,
}


def variant(name: str, n_places: int = N_PLACES) -> Variant:
    """The variant ``name`` of a drive of ``n_places`` places (see the module doc)."""
    if name not in VARIANTS:
        raise ValueError(f"unknown variant {name!r} (known: {', '.join(VARIANTS)})")
    return VARIANTS[name](n_places)


def source_places(v: Variant) -> npt.NDArray[np.int64]:
    """The source place of every frame of ``v`` (its ``places``)."""
    return v.places


def along_track_xy(places: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Synthetic (x, y) metres of source places: ``METRES_PER_PLACE`` apart along a gentle curve
    (a circle of 5 km radius), fractional places in between."""
    s = np.asarray(places, dtype=np.float64) * METRES_PER_PLACE
    radius = 5000.0
    return np.stack([radius * np.sin(s / radius), radius * (1 - np.cos(s / radius))], axis=1)


def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _noisy_png(data: bytes, rng: np.random.Generator) -> bytes:
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError("a source frame does not decode")
    out = np.clip(np.round(img.astype(np.float64) + rng.normal(0.0, NOISE_SIGMA, img.shape)), 0, 255).astype(img.dtype)
    ok, buf = cv2.imencode(".png", out)
    if not ok:
        raise ValueError("PNG encoding failed")
    return bytes(buf)


def write_variant(source: str | os.PathLike[str], v: Variant, out: str | os.PathLike[str], *,
                  start_ns: int | None = None, positions: bool = False, seed: int = 0) -> Path:
    """Write variant ``v`` of the source drive ``source`` as an MCAP log at ``out``: the camera
    topic's messages in the source's schema with the variant's stamps (header stamp = log time =
    publish time = ``start_ns`` + the variant's stamp; default: the source's first log time), and
    with ``positions`` a ``/odom`` topic (see the module doc). Deterministic for a ``seed``."""
    from memlog.io import McapLogWriter, open_log

    rng = np.random.default_rng(seed)
    with open_log(source) as reader:
        msgs = list(reader.messages([TOPIC]))
        start = reader.info().start_ns if start_ns is None else start_ns
        profile = reader.profile
    if not msgs:
        raise ValueError(f"{source}: no messages on {TOPIC}")
    if int(v.places.max(initial=0)) >= len(msgs):
        raise ValueError(f"{source} has {len(msgs)} places; the variant needs {int(v.places.max()) + 1}")
    assert start is not None
    store = _typestore()
    ctype = msgs[0].channel.msgtype
    decoded = {}
    xy = along_track_xy(v.places) + rng.normal(0.0, ODOM_NOISE_M, (len(v), 2)) if positions else None
    with McapLogWriter(out, profile=profile) as w:
        odom_ch = _odometry_channel(w, store) if positions else None
        for j, (p, t) in enumerate(zip(v.places, v.stamps_ns)):
            src = msgs[int(p)]
            m = decoded.get(int(p))
            if m is None:
                m = decoded[int(p)] = store.deserialize_cdr(src.data, ctype)
            stamp = int(start + t)
            sec, nsec = divmod(stamp, 1_000_000_000)
            header = store.types["std_msgs/msg/Header"](
                stamp=store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=m.header.frame_id)
            data = np.frombuffer(_noisy_png(bytes(m.data), rng), np.uint8) if v.noisy[j] else m.data
            msg = store.types[ctype](header=header, format=m.format, data=data)
            w.write(w.channel_for(src.channel), stamp, bytes(store.serialize_cdr(msg, ctype)), sequence=j)
            if odom_ch is not None and xy is not None:
                _write_odometry(w, odom_ch, store, stamp, header, xy[j])
    return Path(out)


def with_odometry(source: str | os.PathLike[str], places: npt.ArrayLike, out: str | os.PathLike[str], *,
                  seed: int = 0) -> Path:
    """Copy the log ``source`` (its camera topic, messages unchanged) to ``out`` with the ``/odom``
    topic ``positions=True`` writes: one message per frame, at its log time and header stamp, at
    the along-track position of its source place ``places[j]`` (:func:`along_track_xy`, 5 cm noise):
    the odometry a robot records beside its camera. Deterministic for a ``seed``."""
    from memlog.io import McapLogWriter, open_log

    with open_log(source) as reader:
        msgs = list(reader.messages([TOPIC]))
        profile = reader.profile
    p = np.asarray(places, dtype=np.float64)
    if len(msgs) != len(p):
        raise ValueError(f"{source}: {len(msgs)} frames on {TOPIC}, but {len(p)} places")
    store = _typestore()
    xy = along_track_xy(p) + np.random.default_rng(seed).normal(0.0, ODOM_NOISE_M, (len(p), 2))
    with McapLogWriter(out, profile=profile) as w:
        odom_ch = _odometry_channel(w, store)
        for j, m in enumerate(msgs):
            w.write(w.channel_for(m.channel), m.log_time, m.data, sequence=j)
            header = store.deserialize_cdr(m.data, m.channel.msgtype).header
            _write_odometry(w, odom_ch, store, m.log_time, header, xy[j])
    return Path(out)


ODOM_TYPE = "nav_msgs/msg/Odometry"


def _odometry_channel(w: Any, store: Any) -> int:
    """The ``/odom`` channel (``nav_msgs/msg/Odometry``, CDR) added to the MCAP writer ``w``."""
    text, _ = store.generate_msgdef(ODOM_TYPE, ros_version=2)
    return int(w.add_channel(ODOM_TOPIC, "cdr", w.add_schema(ODOM_TYPE, "ros2msg", text.encode())))


def _write_odometry(w: Any, channel: int, store: Any, stamp: int, header: Any, xy: npt.NDArray[np.float64]) -> None:
    """One odometry message at ``xy`` (header ``header``) on ``channel`` at log time ``stamp``."""
    w.write(channel, stamp, bytes(store.serialize_cdr(_odometry(store, header, xy), ODOM_TYPE)))


def _odometry(store: Any, header: Any, xy: npt.NDArray[np.float64]) -> Any:
    T = store.types
    point = T["geometry_msgs/msg/Point"](x=float(xy[0]), y=float(xy[1]), z=0.0)
    quat = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    cov = np.zeros(36, dtype=np.float64)
    pose = T["geometry_msgs/msg/PoseWithCovariance"](pose=T["geometry_msgs/msg/Pose"](position=point, orientation=quat),
                                                      covariance=cov)
    vec = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    twist = T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](linear=vec, angular=vec),
                                                        covariance=cov)
    return T["nav_msgs/msg/Odometry"](header=header, child_frame_id="base_link", pose=pose, twist=twist)


def truth(query: Variant, reference: Variant, tolerance: int = 1) -> dict[str, Any]:
    """Ground truth of ``query`` against ``reference`` by source place: ``matches[q]`` = the
    reference frames whose place is within ``tolerance`` of query frame ``q``'s place."""
    rp = reference.places
    order = np.argsort(rp, kind="stable")
    sp = rp[order]
    matches = []
    for p in query.places:
        a, b = np.searchsorted(sp, p - tolerance), np.searchsorted(sp, p + tolerance, side="right")
        matches.append(sorted(int(i) for i in order[a:b]))
    return {"matches": matches, "tolerance_places": tolerance, "query_variant": query.name,
            "reference_variant": reference.name, "query_places": [int(p) for p in query.places],
            "reference_places": [int(p) for p in rp]}


def write_truth(path: str | os.PathLike[str], query: Variant, reference: Variant, tolerance: int = 1) -> Path:
    """:func:`truth` as JSON (the format of ``nordland_dev_truth.json``, with the place lists)."""
    p = Path(path)
    p.write_text(json.dumps(truth(query, reference, tolerance)) + "\n", encoding="utf-8")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="directory for the logs and truth files (must exist)")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--drives", nargs="+", default=list(DRIVES), choices=list(DRIVES),
                    help="which source drives to make variants of (default both)")
    ap.add_argument("--reference-variant", default="base", choices=list(VARIANTS),
                    help="the reference variant the winter truth files are computed against (default base)")
    ap.add_argument("--places", type=int, default=N_PLACES, help="first N places only")
    ap.add_argument("--positions", action="store_true", help="also write a /odom topic with synthetic positions")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    if not a.out.is_dir():
        ap.error(f"--out {a.out}: no such directory")
    ref = variant(a.reference_variant, a.places)
    for drive in a.drives:
        for n, name in enumerate(a.variants):
            v = variant(name, a.places)
            out = a.out / f"nordland_{drive}_{name}.mcap"
            write_variant(SHARED / DRIVES[drive], v, out, positions=a.positions, seed=a.seed * 1000 + n)
            line = f"{out} ({len(v)} frames, {v.description})"
            if drive == "winter":
                t = write_truth(a.out / f"nordland_truth_{name}_vs_{ref.name}.json", v, ref)
                line += f"; truth {t}"
            print(line)  # a developer tool's report (not library code)
    return 0


if __name__ == "__main__":
    sys.exit(main())
