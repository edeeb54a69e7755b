"""Leftovers of the damage sweep.

1. A path that is a symlink loop (an input log, another input file or an output) is a usage
   error (exit 2) naming the path, in every command, not an internal error.
2. A ROS 2 ``.db3`` row whose ``timestamp`` is negative or not an integer (SQLite is dynamically
   typed) keeps its message: at the message's header stamp, else a neighbouring row's time, with
   a warning naming file, topic and row; log-time order and frame numbering follow, and the run
   still reports damaged input (exit 3).
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import sqlite3
import struct
from pathlib import Path
from typing import Any

import pytest

from memlog.errors import OutputPathError, SymlinkLoopError, UsageError
from memlog.io import open_log
from memlog.io.atomic import check_output, same_path
from tests.conftest import FIXTURES, shared

DEMO = FIXTURES / "demo.mcap"
CAM = "/cam0/image_raw/compressed"


def _cli(*args: str) -> tuple[int, str, str]:
    """``memlog ARGS`` in this process: (exit code, stdout, stderr)."""
    from memlog.cli.app import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(list(args))
        except SystemExit as exc:
            code = int(exc.code or 0)
    return code, out.getvalue(), err.getvalue()


# -- 1. symlink loops -------------------------------------------------------------------------
@pytest.fixture()
def loop(tmp_path: Path) -> Path:
    """``tmp/loops/loopa -> loopb -> loopa`` (relative links, as in the report)."""
    d = tmp_path / "loops"
    d.mkdir()
    os.symlink("loopb", d / "loopa")
    os.symlink("loopa", d / "loopb")
    return d / "loopa"


# (command line, what the message says about the loop); {loop} is the loop, {out} an empty directory
LOOP_COMMANDS = [
    (["inspect", "{loop}"], "{loop}: is a symlink loop"),
    (["convert", "{loop}", "-o", "{out}/x.mcap"], "{loop}: is a symlink loop"),
    (["convert", "{demo}", "-o", "{loop}"], "-o {loop}: is a symlink loop"),
    (["convert", "{demo}", "-o", "{loop}/x.mcap"], "-o {loop}/x.mcap: passes through the symlink loop {loop}"),
    (["score", "{loop}", "-o", "{out}/x.mcap"], "{loop}: is a symlink loop"),
    (["score", "{demo}", "-o", "{loop}"], "-o {loop}: is a symlink loop"),
    (["map", "{loop}", "-o", "{out}/x.mcap"], "{loop}: is a symlink loop"),
    (["map", "{demo}", "-o", "{loop}"], "-o {loop}: is a symlink loop"),
    (["map", "{demo}", "-o", "{out}/x.mcap", "--scores", "{loop}"], "{loop}: is a symlink loop"),
    (["localize", "{loop}", "{demo}", "-o", "{out}/m.parquet"], "{loop}: is a symlink loop"),
    (["localize", "{out}/map.parquet", "{loop}", "-o", "{out}/m.parquet"], "{loop}: is a symlink loop"),
    (["localize", "{out}/map.parquet", "{demo}", "-o", "{loop}/m.parquet"],
     "-o {loop}/m.parquet: passes through the symlink loop {loop}"),
    (["evaluate", "--reference", "{loop}", "--query", "{demo}", "-o", "{out}/ev"], "{loop}: is a symlink loop"),
    (["evaluate", "--reference", "{demo}", "--query", "{loop}", "-o", "{out}/ev"], "{loop}: is a symlink loop"),
    (["evaluate", "--reference", "{demo}", "--query", "{demo}", "--truth", "{loop}", "-o", "{out}/ev"],
     "{loop}: is a symlink loop"),
    (["evaluate", "--reference", "{demo}", "--query", "{demo}", "-o", "{loop}"], "-o {loop}: is a symlink loop"),
    (["batch", "{loop}", "-o", "{out}/b"], "{loop}: is a symlink loop"),
    (["batch", "{demo}", "-o", "{loop}"], "-o {loop}: is a symlink loop"),
    (["batch", "{demo}", "-o", "{out}/b", "--summary", "{loop}"], "--summary {loop}: is a symlink loop"),
]


@pytest.mark.parametrize("argv,said", LOOP_COMMANDS, ids=[" ".join(a) for a, _ in LOOP_COMMANDS])
def test_a_symlink_loop_is_a_usage_error_in_every_command(argv: list[str], said: str, loop: Path,
                                                          tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    names = {"loop": str(loop), "out": str(out), "demo": str(DEMO)}
    code, _, err = _cli(*[a.format(**names) for a in argv])
    assert code == 2, err
    assert f"memlog {argv[0]}: error: {said.format(**names)}" in err, err
    assert "internal error" not in err and "Traceback" not in err
    assert list(out.iterdir()) == []  # nothing was made
    assert os.readlink(loop) == "loopb"  # the loop is left as it was


def test_symlink_loops_in_the_library(loop: Path, tmp_path: Path) -> None:
    with pytest.raises(SymlinkLoopError, match="is a symlink loop"):
        open_log(loop)
    with pytest.raises(SymlinkLoopError, match=f"-o {loop}: is a symlink loop"):
        check_output(loop, [DEMO])
    with pytest.raises(SymlinkLoopError, match=f"--annotate {loop}/x.mcap: passes through the symlink loop"):
        check_output(loop / "x.mcap", [DEMO], flag="--annotate")
    with pytest.raises(SymlinkLoopError, match=f"{loop}: is a symlink loop"):
        check_output(tmp_path / "x.mcap", [DEMO, loop])
    assert issubclass(SymlinkLoopError, UsageError)
    assert not same_path(loop, DEMO) and not same_path(DEMO, loop)  # no exception: it is not that file


def test_ordinary_symlinks_still_work(tmp_path: Path) -> None:
    link = tmp_path / "drive.mcap"
    link.symlink_to(DEMO)
    code, out, err = _cli("inspect", str(link))
    assert code == 0 and "camera topics:" in out, err
    with pytest.raises(OutputPathError, match="would overwrite the input"):
        check_output(link, [DEMO])
    code, _, err = _cli("convert", str(DEMO), "-o", str(link))
    assert code == 2 and "would overwrite the input" in err


# -- 2. .db3 rows without a valid timestamp ------------------------------------------------------
def _rows(db: Path) -> dict[int, tuple[Any, bytes]]:
    """Row id -> (timestamp, data) straight from sqlite."""
    con = sqlite3.connect(f"file:{db}?immutable=1", uri=True)
    try:
        return {rid: (t, d) for rid, t, d in con.execute("SELECT id, timestamp, data FROM messages")}
    finally:
        con.close()


def _stamp(data: bytes) -> int:
    """The header stamp of a little-endian CDR sensor_msgs message (std_msgs/Header first)."""
    assert data[:2] == b"\x00\x01"  # CDR_LE
    sec, nsec = struct.unpack_from("<iI", data, 4)
    return sec * 1_000_000_000 + nsec


def _with_stamp(data: bytes, ns: int) -> bytes:
    return data[:4] + struct.pack("<iI", ns // 1_000_000_000, ns % 1_000_000_000) + data[12:]


def _damaged_bag(tmp_path: Path, *edits: tuple[str, tuple[Any, ...]]) -> tuple[Path, Path]:
    """A copy of the shared EuRoC ROS 2 sqlite bag with ``edits`` (SQL, parameters) applied;
    (bag directory, its .db3)."""
    src = shared("euroc_micro_ros2_db3")
    d = tmp_path / "bag"
    shutil.copytree(src, d)
    for p in d.iterdir():
        p.chmod(0o644)
    db = next(d.glob("*.db3"))
    con = sqlite3.connect(db)
    for sql, params in edits:
        con.execute(sql, params)
    con.commit()
    con.close()
    return d, db


def _frames(path: Path) -> list[tuple[int, int, int, bytes]]:
    with open_log(path) as log:
        log.quiet_warnings()
        return [(f.index, f.log_time_ns, f.stamp_ns, f.payload.data) for f in log.frames()]


def test_db3_rows_with_a_text_or_negative_timestamp_keep_their_messages(tmp_path: Path) -> None:
    intact = _rows(next(shared("euroc_micro_ros2_db3").glob("*.db3")))
    bag, db = _damaged_bag(tmp_path, ("UPDATE messages SET timestamp = 'noon' WHERE id = 5", ()),
                           ("UPDATE messages SET timestamp = -7 WHERE id = 9", ()))
    with open_log(bag) as log:
        log.quiet_warnings()
        msgs = list(log.messages())
        report = log.report
    assert len(msgs) == len(intact) == 95  # none lost (before: 93, the two rows skipped)
    times = [m.log_time for m in msgs]
    assert times == sorted(times)
    for rid in (5, 9):  # each kept with its own bytes, at its header stamp
        ts, data = intact[rid]
        mine = [m for m in msgs if m.data == data]
        assert len(mine) == 1 and mine[0].log_time == _stamp(data) == ts and mine[0].channel.topic == CAM
    # the same frames, numbered alike, as the intact bag's
    assert _frames(bag) == _frames(shared("euroc_micro_ros2_db3"))
    assert report.retimed_messages == 2 and report.bad_messages == 0 and not report.ok
    for rid, value in ((5, "'noon'"), (9, "-7")):
        assert any(str(db) in w and CAM in w and f"message row {rid}:" in w and f"timestamp {value} " in w
                   and "header stamp" in w for w in report.warnings), report.warnings
    code, out, err = _cli("inspect", str(bag))
    assert code == 3 and "messages:  95" in out and "header stamp" in err, err
    conv = tmp_path / "out.mcap"
    code, _, err = _cli("convert", str(bag), "-o", str(conv))
    assert code == 3 and "internal error" not in err, err
    with open_log(conv) as back:
        assert sorted((m.log_time, m.data) for m in back.messages()) == sorted((m.log_time, m.data) for m in msgs)


def test_a_db3_row_takes_its_place_in_log_time_order_from_its_header_stamp(tmp_path: Path) -> None:
    intact = _rows(next(shared("euroc_micro_ros2_db3").glob("*.db3")))
    between = (intact[30][0] + intact[31][0]) // 2  # row 20's message was stamped between rows 30 and 31
    moved = _with_stamp(intact[20][1], between)
    bag, db = _damaged_bag(tmp_path, ("UPDATE messages SET timestamp = '12:00', data = ? WHERE id = 20", (moved,)))
    frames = _frames(bag)
    data = [f[3] for f in frames]
    order = [rid for rid in sorted(intact) if rid != 20]
    order.insert(order.index(31), 20)
    assert data == [_payload(intact[rid][1] if rid != 20 else moved) for rid in order]
    assert [f[0] for f in frames] == list(range(95))  # frame index = place in log-time order
    at = order.index(20)
    assert frames[at][1] == frames[at][2] == between
    # a window around it numbers it alike (one frame table for every read)
    with open_log(bag) as log:
        log.quiet_warnings()
        window = [(f.index, f.payload.data) for f in log.frames(start_ns=between - 1, end_ns=intact[32][0])]
    assert window == [(at, frames[at][3]), (at + 1, frames[at + 1][3])]


def _payload(cdr: bytes) -> bytes:
    """The image bytes of a sensor_msgs/CompressedImage (CDR, little endian)."""
    from rosbags.typesys import Stores, get_typestore

    msg = get_typestore(Stores.ROS2_HUMBLE).deserialize_cdr(cdr, "sensor_msgs/msg/CompressedImage")
    return bytes(msg.data)


def test_a_db3_row_without_a_header_stamp_takes_a_neighbours_time(tmp_path: Path) -> None:
    intact = _rows(next(shared("euroc_micro_ros2_db3").glob("*.db3")))
    unstamped = {rid: _with_stamp(intact[rid][1], 0) for rid in (1, 40)}
    bag, db = _damaged_bag(
        tmp_path,
        ("UPDATE messages SET timestamp = -1, data = ? WHERE id = 1", (unstamped[1],)),  # the first row
        ("UPDATE messages SET timestamp = 3.5, data = ? WHERE id = 40", (unstamped[40],)),
        ("UPDATE messages SET timestamp = 'x', data = 'not a blob' WHERE id = 60", ()),  # no message to keep
    )
    with open_log(bag) as log:
        log.quiet_warnings()
        msgs = list(log.messages())
        report = log.report
    want = [unstamped.get(rid, intact[rid][1]) for rid in sorted(intact) if rid != 60]
    assert [m.data for m in msgs] == want  # every message with a body kept, in the order recorded
    by_data = {m.data: m.log_time for m in msgs}
    assert by_data[unstamped[40]] == intact[39][0]  # the previous row's time
    assert by_data[unstamped[1]] == intact[2][0]  # no row before it: the next row's time
    assert report.retimed_messages == 2 and report.bad_messages == 1 and not report.ok
    text = "\n".join(report.warnings)
    assert f"{db}: topic {CAM}: message row 40: timestamp 3.5 is not a time" in text
    assert f"previous row's time {intact[39][0]}" in text
    assert f"{db}: topic {CAM}: message row 1: timestamp -1 is not a time" in text
    assert f"next row's time {intact[2][0]}" in text
    assert "message row 60: timestamp 'x' is not a time and its data is not a blob; skipped" in text
    assert [f[0] for f in _frames(bag)] == list(range(94))
