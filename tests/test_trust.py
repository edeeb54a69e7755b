"""Trust: no command writes over its inputs, every mistake in a command line is a usage error
(exit 2, naming the flag) before any work, caches are refused when made from other inputs, damage
means exit 3 everywhere, and failures that are not damage stop the run (exit 1)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from memlog.errors import ConfigError, ModelError
from memlog.io import FrameWindow
from memlog.outputs.descriptor_table import read_descriptors
from memlog.scoring.config import ScoreConfig, load_config
from memlog.selection.config import SelectionConfig
from memlog.steps.localize import LocalizeConfig, localize
from memlog.steps.map import MapConfig, make_map
from memlog.steps.score import score
from tests.conftest import FIXTURES, ROOT

DEMO = FIXTURES / "demo.mcap"
COMP = "/camera/image/compressed"
RAW = "/camera/image_raw"


def _cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "memlog", *args], capture_output=True, text=True, cwd=cwd, env=env)


def _sha(path: Path) -> str:
    if path.is_dir():
        return hashlib.sha256(b"".join(_sha(p).encode() for p in sorted(path.rglob("*")) if p.is_file())).hexdigest()
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def demo_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A map of demo.mcap's compressed frames (thresholds 0: every frame; paper rule: no CNN wait)."""
    d = tmp_path_factory.mktemp("map")
    scored = d / "all.mcap"
    score(DEMO, scored, ScoreConfig(all_scores=True), FrameWindow((COMP,)))
    res = make_map(DEMO, d / "map.mcap", MapConfig(select=SelectionConfig(mode="paper", mt=0, st=0, et=0),
                                                   topics=(COMP,)), scores=scored)
    assert res.descriptors is not None
    return res.descriptors


# -- never over an input ----------------------------------------------------------------------------
def test_localize_never_writes_over_its_inputs(demo_map: Path, tmp_path: Path) -> None:
    query = tmp_path / "query.mcap"
    shutil.copyfile(DEMO, query)
    before = (_sha(query), _sha(demo_map))
    for flag, target in (("--annotate", query), ("--annotate", demo_map), ("-o", demo_map),
                         ("--query-descriptors", query), ("--query-descriptors", demo_map)):
        args = ["localize", str(demo_map), str(query), "-o", str(tmp_path / "m.parquet"), "-t", RAW]
        if flag == "-o":
            args[4] = str(target)
        else:
            args += [flag, str(target)]
        r = _cli(*args)
        assert r.returncode == 2 and flag in r.stderr and "overwrite" in r.stderr, (flag, r.stderr)
    link = tmp_path / "link.mcap"
    link.symlink_to(query)
    r = _cli("localize", str(demo_map), str(query), "-o", str(tmp_path / "m.parquet"), "--annotate", str(link))
    assert r.returncode == 2 and "overwrite" in r.stderr
    assert (_sha(query), _sha(demo_map)) == before
    assert not (tmp_path / "m.parquet").exists()


def test_outputs_inside_a_bag_directory_are_refused(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    shutil.copytree(FIXTURES / "ros2_sqlite", bag)
    before = _sha(bag)
    r = _cli("convert", str(bag), "-o", str(bag / "x.mcap"))
    assert r.returncode == 2 and "inside the input" in r.stderr
    assert _sha(bag) == before and not (bag / "x.mcap").exists()


def test_missing_output_directory_is_refused_everywhere(demo_map: Path, tmp_path: Path) -> None:
    missing = tmp_path / "nope" / "x"
    for args in (["convert", str(DEMO), "-o", f"{missing}.mcap"],
                 ["score", str(DEMO), "-o", f"{missing}.mcap"],
                 ["map", str(DEMO), "-o", f"{missing}.mcap"],
                 ["localize", str(demo_map), str(DEMO), "-o", f"{missing}.parquet"],
                 ["evaluate", "--reference", str(DEMO), "--query", str(DEMO), "-o", str(missing)]):
        r = _cli(*args)
        assert r.returncode == 2 and "does not exist" in r.stderr and "Traceback" not in r.stderr, args
    assert not (tmp_path / "nope").exists()


# -- mistakes reported before any work --------------------------------------------------------------
@pytest.mark.parametrize("args,flag", [
    (["score", str(DEMO), "-o", "OUT.mcap", "--stride", "0"], "--stride"),
    (["score", str(DEMO), "-o", "OUT.mcap", "--stride", "-2"], "--stride"),
    (["score", str(DEMO), "-o", "OUT.mcap", "--start", "abc"], "--start"),
    (["score", str(DEMO), "-o", "OUT.mcap", "--threads", "-1"], "--threads"),
    (["score", str(DEMO), "-o", "OUT.mcap", "--workers", "0"], "--workers"),
    (["score", str(DEMO), "-o", "OUT.mcap", "--mt", "2"], "--mt"),
    (["score", str(DEMO), "-o", "OUT.mcap", "--duplicates", "near"], "--fast"),
    (["score", str(DEMO), "-o", "OUT.mcap", "--near-distance", "0"], "--near-distance"),
    (["score", str(DEMO), "-o", "OUT.mcap", "-t", "/no/such/topic"], "/no/such/topic"),
    (["score", str(DEMO), "-o", "OUT.mcap", "--start", "+5", "--end", "+1"], "--start/--end"),
    (["map", str(DEMO), "-o", "OUT.mcap", "--dedup", "-1"], "--dedup"),
    (["map", str(DEMO), "-o", "OUT.mcap", "--keep-fraction", "2"], "--keep-fraction"),
    (["map", str(DEMO), "-o", "OUT.mcap", "--jpeg-quality", "500"], "--jpeg-quality"),
    (["map", str(DEMO), "-o", "OUT.mcap", "--keep-topic", "/nope"], "--keep-topic"),
    (["map", str(DEMO), "-o", "OUT.mcap", "--select", "paper", "--spacing-m", "5"], "--spacing-m"),
    (["map", str(DEMO), "-o", "OUT.mcap", "--descriptor", "sift"], "--descriptor"),
    (["map", str(DEMO), "-o", "OUT.mcap", "--candidates", "0"], "--candidates"),
    (["map", str(DEMO), "-o", "OUT.mcap", "--candidates", "some"], "--candidates"),
    (["map", str(DEMO), "-o", "OUT.mcap", "--select", "paper", "--candidates", "2"], "--candidates"),
    (["map", str(DEMO), "-o", "OUT.mcap", "--scores", str(FIXTURES / "ros1.mcap")], "--scores"),
    (["evaluate", "--reference", str(DEMO), "--query", str(DEMO), "-o", "OUTDIR", "--seeds", "0"], "--seeds"),
    (["evaluate", "--reference", str(DEMO), "--query", str(DEMO), "-o", "OUTDIR", "--truth", "missing.json"],
     "missing.json"),
])
def test_mistakes_are_usage_errors_before_any_work(args: list[str], flag: str, tmp_path: Path) -> None:
    r = _cli(*args, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert flag in r.stderr and "Traceback" not in r.stderr and "internal error" not in r.stderr
    assert not any(tmp_path.iterdir()), "nothing is written"


def test_logs_with_the_same_name_are_refused_before_any_work(tmp_path: Path) -> None:
    """Two logs named alike would write the same outputs: `score` with several logs and `batch`
    refuse them, naming the output directory and the name."""
    other = tmp_path / "elsewhere"
    other.mkdir()
    shutil.copy(DEMO, other / "demo.mcap")
    out = tmp_path / "out"
    out.mkdir()
    for args in (["score", str(DEMO), str(other / "demo.mcap"), "-o", str(out)],
                 ["batch", str(DEMO), str(other / "demo.mcap"), "-o", str(out)]):
        r = _cli(*args)
        assert r.returncode == 2 and f"-o {out}: several logs are named demo" in r.stderr, (args, r.stderr)
        assert "Traceback" not in r.stderr
    assert not any(out.iterdir())


def test_truth_that_does_not_fit_the_logs_is_refused_before_scoring(tmp_path: Path) -> None:
    for matches, why in (([[0]] * 3, "entries but the query topic has 8 frames"),
                         ([[0]] * 7 + [[99]], "names reference frame 99"),
                         ([[]] * 8, "no query has a true match")):
        truth = tmp_path / "t.json"
        truth.write_text(json.dumps({"matches": matches}))
        r = _cli("evaluate", "--reference", str(DEMO), "--query", str(DEMO), "--reference-topic", COMP,
                 "--query-topic", RAW, "--truth", str(truth), "-o", str(tmp_path / "out"))
        assert r.returncode == 1 and why in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert not (tmp_path / "out" / "reference.scored.mcap").exists()
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    r = _cli("evaluate", "--reference", str(DEMO), "--query", str(DEMO), "--truth", str(bad), "-o", str(tmp_path / "o"))
    assert r.returncode == 1 and "bad.json" in r.stderr and "invalid JSON" in r.stderr
    f = tmp_path / "afile"
    f.write_text("x")
    r = _cli("evaluate", "--reference", str(DEMO), "--query", str(DEMO), "-o", str(f))
    assert r.returncode == 2 and "not a directory" in r.stderr


def test_config_files_are_typed(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text('[score]\nmt = "high"\n')
    with pytest.raises(ConfigError, match=r"c.toml: \[score\] mt: expected a number, got 'high'"):
        load_config(path=cfg)
    cfg.write_text("[select]\nkeep_fraction = 0.3\nspacing = 4\n")
    r = _cli("map", str(DEMO), "-o", str(tmp_path / "m.mcap"), "--config", str(cfg))
    assert r.returncode == 2 and "unknown setting(s) spacing" in r.stderr and "[select]" in r.stderr
    cfg.write_text("[bogus]\nx = 1\n")
    r = _cli("score", str(DEMO), "-o", str(tmp_path / "s.mcap"), "--config", str(cfg))
    assert r.returncode == 2 and "unknown table(s) bogus" in r.stderr


# -- caches that cannot lie -------------------------------------------------------------------------
def test_query_descriptor_cache_is_keyed_on_the_query_log(demo_map: Path, tmp_path: Path) -> None:
    cache = tmp_path / "q.parquet"
    cfg = LocalizeConfig(k=2, window=FrameWindow((RAW,)))
    first = localize(demo_map, DEMO, tmp_path / "a.parquet", cfg, query_descriptors=cache)
    assert not first.query_descriptors_reused and cache.is_file()
    again = localize(demo_map, DEMO, tmp_path / "b.parquet", cfg, query_descriptors=cache)
    assert again.query_descriptors_reused
    other = tmp_path / "other.mcap"  # another query log: the cache was made from demo.mcap
    shutil.copyfile(FIXTURES / "ros2idl.mcap", other)
    res = localize(demo_map, other, tmp_path / "c.parquet", LocalizeConfig(k=2), query_descriptors=cache)
    assert not res.query_descriptors_reused and res.n_queries == 2
    assert read_descriptors(cache).extra["log_identity"]["path"] == str(other.resolve())


def test_match_table_names_map_topics_and_provenance(demo_map: Path, tmp_path: Path) -> None:
    out = tmp_path / "m.parquet"
    localize(demo_map, DEMO, out, LocalizeConfig(k=3, window=FrameWindow((RAW,))))
    t = pq.read_table(out)
    assert set(t.column("ref_topic").to_pylist()) == {COMP}
    md = {k.decode(): json.loads(v) for k, v in t.schema.metadata.items() if k.startswith(b"memlog.")}
    assert md["memlog.map"] == str(demo_map.resolve()) and md["memlog.descriptor"]["kind"] == "thumbnail"
    assert md["memlog.query_log"] == str(DEMO.resolve()) and md["memlog.k"] == 3


def test_map_refuses_scores_of_another_log(tmp_path: Path) -> None:
    scored = tmp_path / "s.mcap"
    score(FIXTURES / "ros2idl.mcap", scored, ScoreConfig(all_scores=True))
    with pytest.raises(ConfigError, match="scored from"):
        make_map(DEMO, tmp_path / "m.mcap", scores=scored)
    assert not (tmp_path / "m.mcap").exists()


# -- damage is exit 3, failures that are not damage are exit 1 ----------------------------------------
def test_localize_on_a_damaged_query_exits_3(demo_map: Path, tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    data = DEMO.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    r = _cli("localize", str(demo_map), str(cut), "-o", str(tmp_path / "m.parquet"), "-t", COMP)
    assert r.returncode == 3 and "damaged" in r.stderr and (tmp_path / "m.parquet").is_file()


def test_a_model_failure_stops_the_run_and_is_not_damage(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from memlog.scoring.scorer import Scorer

    def broken(self: Scorer, cheap: object) -> object:
        raise ModelError("the memorability model failed: out of memory (simulated)")

    monkeypatch.setattr(Scorer, "finish", broken)
    with pytest.raises(ModelError, match="simulated"):
        score(DEMO, tmp_path / "s.mcap", ScoreConfig(all_scores=True), FrameWindow((COMP,)))
    assert not (tmp_path / "s.mcap").exists() and list(tmp_path.iterdir()) == []


def test_a_failed_evaluate_keeps_the_previous_results_and_report(tmp_path: Path) -> None:
    """results.json and report.html of an earlier run stay as they were when a run fails (they are
    replaced only by a run that finished)."""
    from memlog.steps import evaluate as ev

    out = tmp_path / "out"
    out.mkdir()
    (out / "report.html").write_text("old report")
    (out / "results.json").write_text('{"old": true}')
    truth = tmp_path / "t.json"
    truth.write_text(json.dumps({"matches": [[i] for i in range(8)]}))

    class Stop(Exception):
        pass

    def stop(*a: object, **k: object) -> None:
        raise Stop

    orig = ev.make_map  # every run makes its memorable map, after scoring and describing
    ev.make_map = stop  # type: ignore[assignment]
    try:
        with pytest.raises(Stop):
            ev.evaluate(DEMO, DEMO, out, ev.EvaluateConfig(reference_topic=COMP, query_topic=RAW, report=False),
                        truth=truth)
    finally:
        ev.make_map = orig
    assert (out / "report.html").read_text() == "old report"
    assert (out / "results.json").read_text() == '{"old": true}'


# -- the test command on a clone without the shared data ----------------------------------------------
def test_shared_data_tests_skip_on_a_clone_and_fail_in_ci(tmp_path: Path) -> None:
    env = {**os.environ, "MEMLOG_SHARED_DATA": str(tmp_path / "no-shared-data")}
    env.pop("MEMLOG_REQUIRE_SHARED", None)
    args = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/test_entropy.py", "-k",
            "real_frame_1135 and numpy", "-rs"]
    r = subprocess.run(args, cwd=ROOT, env=env, capture_output=True, text=True)
    assert r.returncode == 0 and "1 skipped" in r.stdout and "shared" in r.stdout, r.stdout
    r = subprocess.run(args, cwd=ROOT, env={**env, "MEMLOG_REQUIRE_SHARED": "1"}, capture_output=True, text=True)
    assert r.returncode == 1 and "MEMLOG_REQUIRE_SHARED" in r.stdout, r.stdout


def test_evaluate_metrics_describe_the_map_written(tmp_path: Path) -> None:
    """One selection: the memorable variant's frames are exactly the map's frames (with --dedup and
    a descriptor other than the one dedup uses)."""
    from memlog.scoring.motion import stop_rule
    from memlog.steps.evaluate import EvaluateConfig, evaluate

    truth = tmp_path / "t.json"
    truth.write_text(json.dumps({"matches": [[i] for i in range(8)]}))
    scored = tmp_path / "out" / "reference.scored.mcap"
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "report.html").write_text("a report of an earlier run")
    score(DEMO, scored, ScoreConfig(all_scores=True), FrameWindow((COMP,)))
    res = evaluate(DEMO, DEMO, tmp_path / "out", EvaluateConfig(
        select=SelectionConfig(keep_fraction=0.5, dedup=0.3, still_distance=0.002), reference_topic=COMP,
        query_topic=RAW, seeds=2, report=False), truth=truth)
    kept = read_descriptors(tmp_path / "out" / "map.parquet").frame_index
    # the map's stops and both drives' (what the matching runs along) are found alike: from the log's
    # GNSS fixes (they know every frame), with the same still_distance
    tables = [tmp_path / "out" / "map.parquet", *sorted((tmp_path / "out").glob("reference.*.parquet")),
              *sorted((tmp_path / "out").glob("query.*.parquet"))]
    assert len(tables) == 3 and all(read_descriptors(p).extra["stops"] == stop_rule(0.002, "gnss", "/gps/fix")
                                    for p in tables)
    assert res["memorable"]["frames"] == len(kept)
    saved = json.loads((tmp_path / "out" / "results.json").read_text())
    assert sorted(kept.tolist()) == saved["memorable"]["kept_indices"]
    assert not (tmp_path / "out" / "report.html").exists()  # --no-report: no stale report beside new results
