"""Stops from the log's own motion (issue 30): odometry, poses, twists and GNSS decide where a
drive stood still when they know every frame, the images otherwise (:mod:`memlog.scoring.motion`).

The logs are built here with the fixture script's writer (``fixtures/make_fixtures.py``): a camera
(96x64 PNG frames, 10 Hz) looking at a textured scene, and a motion topic (20 Hz) whose position
or speed is chosen independently of the images. Expectations are in the drive's own terms (which
frames the vehicle stood at), not memlog's: a car standing at a red light while traffic crosses the
view is one stop; a featureless stretch (identical frames) driven at speed is no stop.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType
from typing import Any

import cv2
import numpy as np
import pytest

from memlog.descriptors.extract import describe_log
from memlog.descriptors.registry import make_describer
from memlog.io.positions import MotionTrack
from memlog.scoring.motion import (
    GNSS_STILL_M, MOTION_MAX_GAP_S, STILL_M, STILL_SPEED_MPS, FrameMotion, find_stops, frame_motion, motion_still_rows,
    moving_index, still_rows, stop_rule,
)
from memlog.scoring.scorer import view_vector

T0 = 1_700_000_000_000_000_000
DT = 100_000_000  # camera: 10 Hz
CAM = "/camera/image/compressed"
W, H = 96, 64
STOP = range(10, 30)  # frames the vehicle stands at (it arrives at frame 10, leaves after 29)
N = 40
LAT0, LON0 = 67.28, 14.40


def _scene(width: int, seed: int) -> np.ndarray:
    """A grey scene with texture (blown-up noise): what the camera sees, by column."""
    rng = np.random.default_rng(seed)
    small = rng.uniform(0, 255, size=(H // 4, width // 4)).astype(np.float32)
    return np.asarray(cv2.resize(small, (width, H), interpolation=cv2.INTER_CUBIC).clip(0, 255), np.uint8)


def _frames(standing: str) -> list[np.ndarray]:
    """N frames: the camera pans 8 px per frame except over :data:`STOP`, where it shows either
    ``"traffic"`` (textured blocks crossing the fixed view, 10 px per frame: the images change)
    or ``"blank"`` (one and the same frame: the images do not change)."""
    scene = _scene(W + 8 * N, 0)
    car = _scene(32, 1)[:40, :]
    out = []
    x = 0
    for i in range(N):
        if i not in STOP or i == STOP[0]:
            x = 8 * i
        f = scene[:, x:x + W].copy()
        if i in STOP and standing == "traffic":
            left = -32 + (10 * (i - STOP[0])) % (W + 32)
            a, b = max(0, left), min(W, left + 32)
            if b > a:
                f[12:52, a:b] = car[:, a - left:b - left]
        out.append(f)
    return out


def _metres(positions: str) -> np.ndarray:
    """Where the vehicle is at each camera frame: 1 m per frame, standing over :data:`STOP`
    (``"stop"``), or driving through (``"drive"``)."""
    step = np.ones(N)
    if positions == "stop":
        step[list(STOP)[1:]] = 0.0
    return np.cumsum(step) - 1.0


def _motion_messages(fs: ModuleType, ts: Any, kind: str, metres: np.ndarray, start_s: float = 0.0) -> tuple[str, str, list[tuple[int, Any]]]:
    """The ``kind`` topic at 20 Hz over the drive (from ``start_s`` on): odometry (its pose; its
    twist left zero, as ``benchmarks/drives.py`` writes it), a twist (speed only) or GNSS fixes
    (``metres`` north)."""
    T = ts.types
    t_frames = np.arange(N) * DT
    t_msgs = np.arange(int(start_s * 1e9), (N - 1) * DT + 1, DT // 2)
    pos = np.interp(t_msgs, t_frames, metres)
    # a wheel-speed sensor's speed: the distance since its previous message over the time between
    speed = np.diff(pos, prepend=pos[0] - (pos[1] - pos[0])) / (DT / 2 / 1e9)
    vec = T["geometry_msgs/msg/Vector3"]
    navsat = fs.ros_msgs(ts)[2]
    msgs: list[tuple[int, Any]] = []
    for t, p, v in zip(t_msgs.tolist(), pos.tolist(), speed.tolist()):
        stamp = T0 + int(t)
        header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=stamp // 10**9,
                                                                             nanosec=stamp % 10**9), frame_id="odom")
        if kind == "gnss":
            msgs.append((stamp, navsat(stamp, LAT0 + p / 111_195.0, LON0, 10.0)))
        elif kind == "twist":
            msgs.append((stamp, T["geometry_msgs/msg/TwistStamped"](
                header=header, twist=T["geometry_msgs/msg/Twist"](linear=vec(x=abs(v), y=0.0, z=0.0),
                                                                  angular=vec(x=0.0, y=0.0, z=0.0)))))
        else:
            pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=p, y=0.0, z=0.0),
                                               orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
            zero = T["geometry_msgs/msg/Twist"](linear=vec(x=0.0, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0))
            msgs.append((stamp, T["nav_msgs/msg/Odometry"](
                header=header, child_frame_id="base_link",
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=zero, covariance=np.zeros(36)))))
    topic, typ = {"odometry": ("/odom", "nav_msgs/msg/Odometry"), "twist": ("/vel", "geometry_msgs/msg/TwistStamped"),
                  "gnss": ("/gps/fix", "sensor_msgs/msg/NavSatFix")}[kind]
    return topic, typ, msgs


def _log(fs: ModuleType, path: Path, standing: str, positions: str, kind: str | None = "odometry",
         start_s: float = 0.0) -> Path:
    """A drive log: the frames of :func:`_frames`, and (``kind`` not None) the motion topic of
    :func:`_motion_messages` for the vehicle's :func:`_metres`."""
    ts = fs.typestore(2)
    compressed = fs.ros_msgs(ts)[1]
    topics = [(CAM, "sensor_msgs/msg/CompressedImage",
               [(T0 + i * DT, compressed(T0 + i * DT, fs.png(f), "png")) for i, f in enumerate(_frames(standing))])]
    if kind is not None:
        topics.append(_motion_messages(fs, ts, kind, _metres(positions), start_s))
    fs.write_ros2_mcap(path, topics)
    return path


def _views(standing: str) -> np.ndarray:
    return np.asarray([view_vector(f) for f in _frames(standing)], np.float32)


def _one_stop(mi: np.ndarray) -> bool:
    """Whether the moving index holds the vehicle's stop as one place and advances everywhere else."""
    stop = np.asarray(list(STOP))
    rest = np.setdiff1d(np.arange(N), stop[1:])
    return len(np.unique(mi[stop])) == 1 and bool(np.all(np.diff(mi[rest]) == 1))


@pytest.mark.parametrize("kind", ["odometry", "twist", "gnss"])
def test_standing_with_traffic_in_front_is_one_stop(kind: str, fixture_script: ModuleType, tmp_path: Path) -> None:
    """(a) The motion topic stands over :data:`STOP` while a block crosses the view: the images
    change (the image rule finds no stop there), the log's motion makes it one stop, and the table
    records which topic decided."""
    assert still_rows(_views("traffic"))[list(STOP)[1:]].mean() < 0.5  # the images alone: it moves
    log = _log(fixture_script, tmp_path / "traffic.mcap", "traffic", "stop", kind)
    t, _ = describe_log(log, make_describer("thumbnail"))
    assert t.moving_index is not None and _one_stop(t.moving_index), t.moving_index.tolist()
    topic = {"odometry": "/odom", "twist": "/vel", "gnss": "/gps/fix"}[kind]
    assert t.extra["stops"] == stop_rule(source=kind, topic=topic)
    # without the motion topic, the same frames: the images decide, and the stop is not found
    plain, _ = describe_log(_log(fixture_script, tmp_path / "plain.mcap", "traffic", "stop", None),
                            make_describer("thumbnail"))
    assert plain.moving_index is not None and not _one_stop(plain.moving_index)
    assert plain.extra["stops"] == stop_rule() and plain.extra["stops"]["source"] == "images"


@pytest.mark.parametrize("kind", ["odometry", "twist", "gnss"])
def test_identical_frames_while_driving_are_not_a_stop(kind: str, fixture_script: ModuleType, tmp_path: Path) -> None:
    """(b) One and the same frame over :data:`STOP` while the motion topic drives on at 10 m/s: the
    image rule calls it a stop, the log's motion does not (the moving index advances every frame)."""
    assert still_rows(_views("blank"))[list(STOP)[1:]].all()  # the images alone: it stands
    log = _log(fixture_script, tmp_path / "blank.mcap", "blank", "drive", kind)
    t, _ = describe_log(log, make_describer("thumbnail"))
    assert t.moving_index is not None and t.moving_index.tolist() == list(range(N))
    assert t.extra["stops"]["source"] == kind


def test_without_motion_for_every_frame_the_images_decide(fixture_script: ModuleType, tmp_path: Path) -> None:
    """(c) A log without a motion topic, and one whose odometry starts 3 s into the drive (more
    than MOTION_MAX_GAP_S before it, the motion of the first frames is unknown): the moving index is
    the image rule's, exactly, and the table says the images decided."""
    assert MOTION_MAX_GAP_S < 3.0
    want = moving_index(np.arange(N), still_rows(_views("blank")))
    assert _one_stop(want)  # (identical frames: the image rule's stop)
    for name, kind, start in (("none.mcap", None, 0.0), ("late.mcap", "odometry", 3.0)):
        t, _ = describe_log(_log(fixture_script, tmp_path / name, "blank", "drive", kind, start),
                            make_describer("thumbnail"))
        assert t.moving_index is not None and t.moving_index.tolist() == want.tolist(), name
        assert t.extra["stops"] == stop_rule(), name
    # still_distance 0 turns stops off whatever decides them
    off, _ = describe_log(_log(fixture_script, tmp_path / "off.mcap", "traffic", "stop"), make_describer("thumbnail"),
                          still_distance=0.0)
    assert off.moving_index is not None and off.moving_index.tolist() == list(range(N))
    assert off.extra["stops"] == stop_rule(0.0) and off.extra["stops"]["source"] == "none"


def test_map_and_localize_find_stops_from_the_odometry(fixture_script: ModuleType, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """(d) ``memlog map`` then ``memlog localize`` through the CLI on a log that stands at a red
    light with traffic in front: the map's segments leave the stop's frames out of the coordinate
    (the selection's ``still_frames``, found from the odometry), the map's table records the
    odometry as the source, and localize finds the query's stop the same way."""
    import pyarrow.parquet as pq
    from mcap.reader import make_reader

    from memlog.cli.app import main
    from memlog.outputs.descriptor_table import read_descriptors
    from tests.stand_in import use_stand_in

    use_stand_in(monkeypatch)
    log = _log(fixture_script, tmp_path / "drive.mcap", "traffic", "stop")
    assert main(["-q", "map", str(log), "-o", str(tmp_path / "m.mcap"), "--descriptor", "thumbnail"]) == 0
    m = read_descriptors(tmp_path / "m.parquet")
    assert m.extra["stops"] == stop_rule(source="odometry", topic="/odom")
    assert m.moving_index is not None and m.moving_index.tolist() == [
        i if i < STOP[0] else STOP[0] if i in STOP else i - len(STOP) + 1 for i in m.frame_index.tolist()]
    assert sum(1 for i in m.frame_index.tolist() if i in STOP) <= 1  # the stop is one place: one map frame
    with open(tmp_path / "m.mcap", "rb") as fh:
        meta = next(r.metadata for r in make_reader(fh).iter_metadata() if r.name == "memlog_map")
    info = json.loads(meta["selection"])[CAM]["info"]
    assert info["still_frames"] == len(STOP) - 1 and info["stops_from"] == {"source": "odometry", "topic": "/odom"}
    assert main(["-q", "localize", str(tmp_path / "m.parquet"), str(log), "-o", str(tmp_path / "x.parquet")]) == 0
    # along the frames (the default follows the positions the odometry gives both drives), the
    # query's stop is one place too: found from its odometry, as the map recorded (the images move)
    assert main(["-q", "localize", str(tmp_path / "m.parquet"), str(log), "-o", str(tmp_path / "f.parquet"),
                 "--coordinate", "frames", "--query-descriptors", str(tmp_path / "q.parquet")]) == 0
    seq = json.loads(pq.read_table(tmp_path / "f.parquet").schema.metadata[b"memlog.sequence"])
    assert seq["coordinate"] == "frames" and seq["standing_rows"] == len(STOP) - 1
    q = read_descriptors(tmp_path / "q.parquet")
    assert q.extra["stops"] == m.extra["stops"] and q.moving_index is not None and _one_stop(q.moving_index)


def _motion(source: str, xyz: Any = None, speed: Any = None, hz: float = 10.0) -> FrameMotion:
    n = len(xyz if xyz is not None else speed)
    return FrameMotion(source, "/m", (np.arange(n) * 1e9 / hz).astype(np.int64),
                       None if xyz is None else np.asarray(xyz, np.float64),
                       None if speed is None else np.asarray(speed, np.float64))


def test_the_motion_rule_and_its_thresholds() -> None:
    """Positions within STILL_M of the stop's first frame stand (a crawl moves a frame every
    STILL_M); GNSS within GNSS_STILL_M; speeds below STILL_SPEED_MPS, or travelled less than
    STILL_M since the stop's first frame, stand; an odometry's unfilled field does not decide."""
    def line(x: Any) -> np.ndarray:
        return np.column_stack([x, np.zeros(len(x)), np.zeros(len(x))])

    crawl = line(np.arange(0, 2.0, 0.1))  # 0.1 m per frame: a frame moves every 0.3 m (the first >= 0.25)
    got = motion_still_rows(_motion("odometry", crawl))
    assert np.flatnonzero(~got).tolist() == [0, 3, 6, 9, 12, 15, 18] and STILL_M == 0.25
    jitter = line(0.3 * np.sin(np.arange(30.0)))  # a standing receiver's fix, wandering by 0.3 m
    assert motion_still_rows(_motion("gnss", jitter))[1:].all() and not motion_still_rows(_motion("pose", jitter)).all()
    assert GNSS_STILL_M == 0.5
    # speeds: noise below 0.1 m/s stands however long; then 1 m/s at 10 Hz moves a frame every 0.3 m
    # (the first once 0.25 m are travelled since frame 0: 0.25 m braking from 5 m/s, 0.05 m speeding up)
    speed = np.r_[5.0, np.full(10, 0.05), np.full(10, 1.0)]
    got = motion_still_rows(_motion("twist", speed=speed))
    assert got[1:11].all() and np.flatnonzero(~got[11:]).tolist() == [0, 3, 6, 9] and STILL_SPEED_MPS == 0.1
    # odometry whose twist is zero while its pose moves: the pose decides; a pose left at 0 while
    # the twist moves: the twist decides
    assert not motion_still_rows(_motion("odometry", line(np.arange(10.0)), np.zeros(10))).any()
    assert not motion_still_rows(_motion("odometry", line(np.zeros(10)), np.full(10, 10.0))).any()
    assert motion_still_rows(_motion("odometry", line(np.zeros(10)), np.zeros(10)))[1:].all()
    # motion unknown at one frame: the images decide
    views = _views("blank")
    part = _motion("odometry", line(np.r_[np.arange(N - 1.0), np.nan]))
    assert find_stops(N, views, part).source == "images"
    assert find_stops(N, views, part).still.tolist() == still_rows(views).tolist()
    assert find_stops(N, views, _motion("odometry", line(np.arange(float(N))))).source == "odometry"


def test_the_first_motion_topic_that_knows_every_frame_decides() -> None:
    """Odometry before poses before twists before GNSS; a topic with a gap longer than
    MOTION_MAX_GAP_S (or that starts later) does not know every frame and the next one decides."""
    t = np.arange(50) * DT
    gap = np.r_[t[:10], t[40:]]
    odom = MotionTrack("/odom", "odometry", gap, np.zeros((len(gap), 3)), np.zeros(len(gap)))
    gps = MotionTrack("/fix", "gnss", t, np.zeros((50, 3)))
    m = frame_motion([odom, gps], t)
    assert m is not None and (m.source, m.topic) == ("gnss", "/fix")
    m = frame_motion([odom, gps], t[:10])
    assert m is not None and m.source == "odometry"
    assert frame_motion([odom], t) is None


def test_the_segments_leave_the_motion_s_stops_out(tmp_path: Path) -> None:
    """Selection and matching find stops with the one function: the segments of a table with the
    log's motion stand where its moving index stands (odometry, whatever the images say)."""
    from memlog.selection import ScoreTable
    from memlog.selection.segment import SegmentConfig, cut_segments

    views = _views("traffic")
    xyz = np.column_stack([_metres("stop"), np.zeros(N), np.zeros(N)])
    motion = FrameMotion("odometry", "/odom", np.arange(N) * DT, xyz)
    table = ScoreTable(index=np.arange(N), t_ns=np.arange(N) * DT, ms=np.full(N, 0.7), ss=np.ones(N), es=np.full(N, 0.5),
                       view=views, motion=motion)
    seg, coord, info = cut_segments(table, SegmentConfig(keep_fraction=0.5))
    assert info["still_frames"] == len(STOP) - 1 and info["stops_from"] == {"source": "odometry", "topic": "/odom"}
    assert coord is not None and len(np.unique(coord[list(STOP)])) == 1  # the stop lies at one place
    assert _one_stop(moving_index(table.index, find_stops(N, views, motion).still))
    # the same table without the motion: the image rule, the traffic moves
    _, coord, info = cut_segments(ScoreTable(index=table.index, t_ns=table.t_ns, ms=table.ms, ss=table.ss, es=table.es,
                                             view=views), SegmentConfig(keep_fraction=0.5))
    assert "stops_from" not in info and info["still_frames"] < (len(STOP) - 1) / 2


def test_the_drive_variants_odometry_finds_their_stops(tmp_path: Path) -> None:
    """``benchmarks/drives.py``'s ``stops`` variant with ``positions=True`` (an ``/odom`` topic with
    5 cm of noise per message, its twist zero): its stops (a place repeated with sensor noise) are
    found from the odometry, frame for frame where the place repeats."""
    from benchmarks.drives import variant, write_variant
    from tests.conftest import shared

    v = variant("stops")
    log = write_variant(shared("nordland_dev_winter.mcap"), v, tmp_path / "stops.mcap", positions=True)
    t, _ = describe_log(log, make_describer("thumbnail"))
    assert t.extra["stops"]["source"] == "odometry" and t.moving_index is not None
    repeat = np.r_[False, v.places[1:] == v.places[:-1]]
    assert t.moving_index.tolist() == moving_index(np.arange(len(v)), repeat).tolist()
