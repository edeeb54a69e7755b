"""The staged scores ``memlog evaluate`` keeps in its output directory (``memlog.steps.score_cache``):
a round trip gives back what :func:`staged_scores_and_looks` computed, the key follows the inputs and
settings, a damaged file is scored again, and a rerun of ``evaluate`` scores nothing and reports the
same results."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from memlog.io.base import FrameWindow
from memlog.selection.config import SelectionConfig
from memlog.steps.map import MapConfig, staged_scores_and_looks
from memlog.steps.score_cache import cache_key, cached_staged_scores
from tests.conftest import FIXTURES

DEMO = FIXTURES / "demo.mcap"
COMP = "/camera/image/compressed"


def _untimed(recs: dict) -> str:
    """The records as JSON without their timing fields (a second scoring takes another time)."""
    return json.dumps({t: [{k: v for k, v in r.items() if k != "timing_ms"} for r in rs] for t, rs in recs.items()},
                      sort_keys=True)


def _same_looks(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for t in a:
        assert a[t].keys() == b[t].keys()
        for i in a[t]:
            for x, y in zip(a[t][i], b[t][i]):
                assert (x is None) == (y is None)
                if x is not None:
                    np.testing.assert_array_equal(x, y)


def test_round_trip_and_reuse(tmp_path: Path) -> None:
    cfg = MapConfig(topics=(COMP,), descriptor=None)
    window = FrameWindow((COMP,))
    want, want_looks, _ = staged_scores_and_looks(str(DEMO), cfg, window)
    recs, looks, report = cached_staged_scores(tmp_path, "reference", str(DEMO), cfg, window)
    assert report is not None  # computed
    assert _untimed(recs) == _untimed(want)
    assert want_looks is not None and looks is not None
    _same_looks(looks, want_looks)
    files = list(tmp_path.glob("reference.staged.*.npz"))
    assert len(files) == 1
    stamp = files[0].stat().st_mtime_ns
    again, again_looks, report2 = cached_staged_scores(tmp_path, "reference", str(DEMO), cfg, window)
    assert report2 is None and files[0].stat().st_mtime_ns == stamp  # read, not scored
    assert json.dumps(again, sort_keys=True) == json.dumps(recs, sort_keys=True)  # exactly what was stored
    assert again_looks is not None
    _same_looks(again_looks, want_looks)


def test_the_key_follows_inputs_and_settings(tmp_path: Path) -> None:
    cfg = MapConfig(topics=(COMP,), descriptor=None)
    w = FrameWindow((COMP,))
    k = cache_key(DEMO, cfg, w)
    assert k == cache_key(DEMO, cfg, w)
    assert k != cache_key(DEMO, replace(cfg, select=SelectionConfig(keep_fraction=0.5)), w)
    assert k != cache_key(DEMO, cfg, FrameWindow((COMP,), stride=2))
    copy = tmp_path / "demo.mcap"
    shutil.copyfile(DEMO, copy)
    assert k != cache_key(copy, cfg, w)  # another log (path, size, time)


def test_a_damaged_cache_is_scored_again(tmp_path: Path) -> None:
    cfg = MapConfig(topics=(COMP,), descriptor=None)
    w = FrameWindow((COMP,))
    cached_staged_scores(tmp_path, "reference", str(DEMO), cfg, w)
    (f,) = tmp_path.glob("reference.staged.*.npz")
    f.write_bytes(b"not an npz")
    recs, _looks, report = cached_staged_scores(tmp_path, "reference", str(DEMO), cfg, w)
    assert report is not None and recs[COMP]
    np.load(f, allow_pickle=False).close()  # replaced by a good one


def test_evaluate_reruns_without_scoring(tmp_path: Path) -> None:
    from memlog.steps.evaluate import EvaluateConfig, evaluate

    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps({"matches": [[i] for i in range(8)]}))
    out = tmp_path / "eval"
    cfg = EvaluateConfig(select=SelectionConfig(keep_fraction=0.5), reference_topic=COMP,
                         query_topic="/camera/image_raw", seeds=2, report=False)
    first = evaluate(DEMO, DEMO, out, cfg, truth=truth)
    caches = sorted(out.glob("reference*.staged.*.npz"))
    # one staged cache: the memorable map's scoring (every other map is a mask of the described drive)
    assert {p.name.split(".staged.")[0] for p in caches} == {"reference"}
    stamps = [p.stat().st_mtime_ns for p in caches]
    second = evaluate(DEMO, DEMO, out, cfg, truth=truth)
    assert [p.stat().st_mtime_ns for p in caches] == stamps
    for row in ("full", "memorable", "uniform"):
        assert second[row]["recall@1"] == pytest.approx(first[row]["recall@1"])
        assert second[row]["frames"] == first[row]["frames"]
