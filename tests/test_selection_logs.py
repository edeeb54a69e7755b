"""Selection modes on real logs: segments by distance (a fixture with GPS), by time and by view
change, the redundancy filter, and empty/short logs. Scores are given as records (the pipeline
reuses a scoring run the same way), so these tests exercise selection and map writing only."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from memlog.errors import ConfigError, MemlogError
from memlog.io import McapLogWriter, open_log
from memlog.io.positions import read_track
from memlog.outputs.annotated import read_scores
from memlog.selection.config import SelectionConfig
from memlog.steps.map import MapConfig, make_map
from tests.conftest import FIXTURES, repeating_log

DEMO = FIXTURES / "demo.mcap"
COMP = "/camera/image/compressed"


def _records(path: Path, topic: str, ms: list[float], ss: list[float] | None = None,
             es: list[float] | None = None) -> dict[str, list[dict]]:
    with open_log(path) as log:
        frames = list(log.frames([topic]))
    n = len(frames)
    ss = ss or [1.0] * n
    es = es or [0.5] * n
    return {topic: [{"frame_index": f.index, "log_time": f.log_time_ns, "ms": ms[i], "ss": ss[i], "es": es[i],
                     "rejected_by": None} for i, f in enumerate(frames)]}


def _kept(path: Path, topic: str) -> list[int]:
    return [r["frame_index"] for r in read_scores(path).get(topic, [])]


def test_segments_by_distance_keep_one_frame_per_stretch(tmp_path: Path) -> None:
    ms = [0.9, 0.1, 0.2, 0.8, 0.3, 0.95, 0.4, 0.6]
    recs = _records(DEMO, COMP, ms)
    cfg = MapConfig(select=SelectionConfig(keep_fraction=0.5, segment_by="distance"), topics=(COMP,), descriptor=None,
                    candidates="all")  # the exact choice: MS decides between the frames of a stretch
    res = make_map(DEMO, tmp_path / "m.mcap", cfg, scores=recs)
    kept = _kept(tmp_path / "m.mcap", COMP)
    info = res.selections[COMP].info
    assert info["by"] == "distance" and info["n_segments"] == 4
    # independent check: travelled distance of each frame from the GPS track, 4 equal stretches;
    # the GPS stands at fixes 3-5 (fixtures/make_fixtures.py positions()), so frames 4 and 5 are a
    # stop (found from the log's GNSS: memlog.scoring.motion) and their steps (GNSS jitter) add nothing
    assert info["still_frames"] == 2 and info["stops_from"] == {"source": "gnss", "topic": "/gps/fix"}
    with open_log(DEMO) as log:
        track = read_track(log)
        t = [f.log_time_ns for f in log.frames([COMP])]
    assert track is not None
    xy = track.at(t)[:, :2]
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    step[[3, 4]] = 0.0  # into frames 4 and 5
    d = np.concatenate([[0.0], np.cumsum(step)])
    stretch = np.minimum((d / (d[-1] / 4)).astype(int), 3)
    assert info["path_length_m"] == pytest.approx(d[-1], rel=1e-6)
    assert len(set(stretch[kept])) == len(kept), "at most one kept frame per stretch"
    for s in set(stretch):  # the kept frame of each stretch is its most memorable one (other scores equal)
        members = [i for i in range(8) if stretch[i] == s]
        assert max(members, key=lambda i: ms[i]) in kept


def test_segments_by_time(tmp_path: Path) -> None:
    recs = _records(DEMO, COMP, [0.5 + 0.05 * i for i in range(8)])
    cfg = MapConfig(select=SelectionConfig(segment_by="time", spacing_s=0.4), topics=(COMP,), descriptor=None,
                    candidates="all")  # the exact choice: MS decides
    make_map(DEMO, tmp_path / "m.mcap", cfg, scores=recs)
    kept = _kept(tmp_path / "m.mcap", COMP)
    # frames every 0.1 s; the GPS stands at frames 3-5 (a stop, from the log's GNSS: its seconds add
    # nothing), so the time coordinate is 0, .1, .2, .3, .3, .3, .4, .5: windows [0,0.4) (frames 0-5)
    # and [0.4,0.8) (6, 7): the best (latest, highest MS) of each
    assert kept == [5, 7]


def test_segments_by_view_change_and_gap(tmp_path: Path) -> None:
    recs = _records(DEMO, COMP, [0.5] * 8)
    recs[COMP][2]["ss"] = 0.0  # a frame that fails the minimums
    cfg = MapConfig(select=SelectionConfig(segment_by="view", view_distance=0.3), topics=(COMP,), descriptor=None)
    res = make_map(DEMO, tmp_path / "m.mcap", cfg, scores=recs)
    sel = res.selections[COMP]
    # every fixture photo differs from the next, so each frame starts its own view segment
    assert sel.segment_id is not None and len(set(sel.segment_id.tolist())) == 8
    assert _kept(tmp_path / "m.mcap", COMP) == [0, 1, 3, 4, 5, 6, 7]
    assert [g.start_index for g in sel.gaps] == [2]  # the failing place is reported as a gap


def test_redundancy_filter_drops_stops_and_loops(tmp_path: Path) -> None:
    log = tmp_path / "loop.mcap"
    repeating_log(log)
    recs = _records(log, COMP, [0.9] * 8)
    cfg = MapConfig(select=SelectionConfig(mode="paper", mt=0.5, st=0.5, et=0.4, dedup=0.05), topics=(COMP,),
                    descriptor=None)
    res = make_map(log, tmp_path / "m.mcap", cfg, scores=recs)
    sel = res.selections[COMP]
    assert _kept(tmp_path / "m.mcap", COMP) == [0, 1, 4, 5]
    assert sel.duplicates == {2: 1, 3: 1, 6: 0, 7: 1}


def test_short_and_empty_logs(tmp_path: Path) -> None:
    one = tmp_path / "one.mcap"
    with open_log(DEMO) as log, McapLogWriter(one, profile="ros2") as w:
        m = next(log.messages([COMP]))
        w.write_raw(m)
    recs = _records(one, COMP, [0.9])
    res = make_map(one, tmp_path / "m1.mcap", MapConfig(select=SelectionConfig(keep_fraction=0.5)), scores=recs)
    assert res.frames_kept == 1 and res.descriptors is not None
    # a log without camera frames: a clear error, no output
    gps_only = tmp_path / "gps.mcap"
    with open_log(DEMO) as log, McapLogWriter(gps_only, profile="ros2") as w:
        for m in log.messages(["/gps/fix"]):
            w.write_raw(m)
    with pytest.raises(MemlogError):
        make_map(gps_only, tmp_path / "m2.mcap", MapConfig(select=SelectionConfig(keep_fraction=0.5)), scores={})
    assert not (tmp_path / "m2.mcap").exists()
    with pytest.raises(ConfigError):
        SelectionConfig(mode="bogus")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="segment"):
        SelectionConfig(mode="paper", spacing_m=5.0)
