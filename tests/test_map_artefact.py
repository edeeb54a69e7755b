"""The map and its descriptors as one artefact (``memlog/outputs/map_artefact.py``): each records
the other, ``check_map_pair`` tells a Parquet of another run (or a changed one) from the map's
own, and a failed run never leaves a new map beside an old Parquet (``memlog map`` and
``memlog batch`` alike)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from mcap.reader import make_reader

import memlog.outputs.map_artefact as artefact
import memlog.steps.map_log as map_step  # (the map step's writing half builds the table)
from memlog.cli.app import main
from memlog.errors import DescriptorError
from memlog.outputs.descriptor_table import read_descriptors
from memlog.outputs.map_artefact import MapPairError, check_map_pair, descriptor_content_sha256
from memlog.steps.map import MapConfig, make_map
from tests.conftest import FIXTURES, shared

DEMO = FIXTURES / "demo.mcap"
COMP = "/camera/image/compressed"


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _link(map_mcap: Path) -> dict[str, str]:
    """The map's record of its descriptor table, read with the mcap library (not memlog's reader)."""
    with open(map_mcap, "rb") as fh:
        records = {m.name: dict(m.metadata) for m in make_reader(fh, validate_crcs=True).iter_metadata()}
    assert "memlog_map" in records
    return records["memlog_map_descriptors"]


def _recorded_map(parquet: Path) -> tuple[str, str]:
    md = pq.read_schema(parquet).metadata
    return md[b"memlog.map_sha256"].decode(), md[b"memlog.map_file"].decode()


def _map_cli(tmp: Path, name: str, *flags: str, log: Path = DEMO) -> Path:
    out = tmp / f"{name}.mcap"
    assert main(["map", str(log), "-o", str(out), "-q", *flags]) == 0
    assert out.is_file() and out.with_suffix(".parquet").is_file()
    return out


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Two `memlog map` runs of demo.mcap (every frame; every 2nd frame), each with its Parquet."""
    d = tmp_path_factory.mktemp("runs")
    return _map_cli(d, "full", "-t", COMP), _map_cli(d, "half", "-t", COMP, "--stride", "2")


def _copy_pair(src: Path, dst_dir: Path, name: str = "MAP") -> tuple[Path, Path]:
    m, p = dst_dir / f"{name}.mcap", dst_dir / f"{name}.parquet"
    shutil.copyfile(src, m)
    shutil.copyfile(src.with_suffix(".parquet"), p)
    return m, p


def test_map_command_writes_a_pair_that_records_each_other(two_runs: tuple[Path, Path]) -> None:
    for m in two_runs:
        p = m.with_suffix(".parquet")
        check_map_pair(m, p)
        # the Parquet names the map file by its bytes' sha256 and its name ...
        assert _recorded_map(p) == (_sha(m), m.name)
        # ... the map names the Parquet by its content's sha256 and its name
        link = _link(m)
        assert link["scheme"] == "1" and link["descriptors_file"] == p.name
        assert len(link["descriptors_sha256"]) == 64 and link["descriptors_sha256"] == descriptor_content_sha256(p)
        assert read_descriptors(p).extra["map"] == str(m)  # (still a plain descriptor table)
    full, half = two_runs
    assert _link(full)["descriptors_sha256"] != _link(half)["descriptors_sha256"]
    assert [read_descriptors(m.with_suffix(".parquet")).extra["frames_in"] for m in two_runs] == [8, 4]


def test_content_sha256_is_the_tables_not_its_encoding(two_runs: tuple[Path, Path], tmp_path: Path) -> None:
    """Another row-group layout of the same table has the same content sha256; a changed value,
    a changed metadata entry or a dropped row does not."""
    p = two_runs[0].with_suffix(".parquet")
    t = pq.read_table(p)
    want = descriptor_content_sha256(p)
    regrouped = tmp_path / "regrouped.parquet"
    assert t.num_rows > 1
    pq.write_table(t, regrouped, row_group_size=1, use_dictionary=False)
    assert pq.ParquetFile(regrouped).metadata.num_row_groups > 1
    assert descriptor_content_sha256(regrouped) == want == descriptor_content_sha256(t)
    md = dict(t.schema.metadata)
    # the map keys are not content (they are written after the map that records the content)
    assert descriptor_content_sha256(t.replace_schema_metadata({**md, b"memlog.map_sha256": b"0" * 64})) == want
    extra = json.loads(md[b"memlog.extra"])
    changed_meta = t.replace_schema_metadata({**md, b"memlog.extra": json.dumps({**extra, "mode": "x"}).encode()})
    assert descriptor_content_sha256(changed_meta) != want
    ms = t.column("ms").to_pylist()
    ms[0] = None if ms[0] is not None else 0.5
    assert descriptor_content_sha256(t.set_column(t.schema.get_field_index("ms"), t.schema.field("ms"),
                                                  pa.array(ms, pa.float64()))) != want
    assert descriptor_content_sha256(t.slice(1)) != want


def test_parquet_of_another_run_is_refused_naming_both_files(two_runs: tuple[Path, Path], tmp_path: Path) -> None:
    full, half = two_runs
    for m, p in ((full, half.with_suffix(".parquet")), (half, full.with_suffix(".parquet"))):
        with pytest.raises(MapPairError) as err:
            check_map_pair(m, p)
        msg = str(err.value)
        assert f"{p} does not belong to the map {m}" in msg and p.stem + ".mcap" in msg, msg
    # the other run's Parquet copied beside the map under the map's name: still refused
    m, p = _copy_pair(full, tmp_path)
    check_map_pair(m, p)
    shutil.copyfile(half.with_suffix(".parquet"), p)
    with pytest.raises(MapPairError, match=f"{p} does not belong to the map {m}: it was written for a map half.mcap"):
        check_map_pair(m, p)


def test_changed_parquet_or_changed_map_is_refused(two_runs: tuple[Path, Path], tmp_path: Path) -> None:
    m, p = _copy_pair(two_runs[0], tmp_path)
    # a descriptor changed in place, the metadata (which names this map) kept
    t = pq.read_table(p)
    i = t.schema.get_field_index("descriptor")
    desc = np.array(t.column("descriptor").to_pylist(), dtype=np.float32)
    desc[0] = -desc[0]
    col = pa.FixedSizeListArray.from_arrays(pa.array(desc.reshape(-1), pa.float32()), type=t.schema.field(i).type)
    pq.write_table(t.set_column(i, t.schema.field(i), col), p)
    assert _recorded_map(p) == (_sha(m), "full.mcap")  # (the pair was renamed: the sha256 decides)
    with pytest.raises(MapPairError, match=f"the map {m} does not belong to {p}: .* changed after the map was written"):
        check_map_pair(m, p)
    # the map's bytes changed (one byte of its data section)
    m2, p2 = _copy_pair(two_runs[0], tmp_path, "other")
    data = bytearray(m2.read_bytes())
    data[len(data) // 2] ^= 0xFF
    m2.write_bytes(bytes(data))
    with pytest.raises(MapPairError, match=f"{p2} does not belong to the map {m2}"):
        check_map_pair(m2, p2)


def test_files_without_a_link_cannot_be_checked(two_runs: tuple[Path, Path], tmp_path: Path) -> None:
    m, p = _copy_pair(two_runs[0], tmp_path)
    t = pq.read_table(p)
    md = {k: v for k, v in t.schema.metadata.items() if not k.startswith(b"memlog.map_")}
    pq.write_table(t.replace_schema_metadata(md), p)  # as written before maps recorded their pairs
    with pytest.raises(MapPairError, match=f"{p} does not record the map it belongs to"):
        check_map_pair(m, p)
    with pytest.raises(MapPairError, match=f"the map {DEMO} records no descriptor table"):
        check_map_pair(DEMO, two_runs[0].with_suffix(".parquet"))  # not a map at all


def _leftovers(d: Path) -> list[str]:
    return sorted(x.name for x in d.iterdir() if x.name.startswith("."))


def _old_pair(two_runs: tuple[Path, Path], d: Path) -> tuple[Path, Path, dict[str, str]]:
    m, p = _copy_pair(two_runs[1], d)  # the earlier run: every 2nd frame
    check_map_pair(m, p)
    return m, p, {"map": _sha(m), "parquet": _sha(p)}


def _no_mismatched_pair(m: Path, p: Path, old: dict[str, str]) -> str:
    """What a failed run left: the old pair intact and matching, or neither file."""
    if not m.exists() and not p.exists():
        return "neither"
    assert m.exists() and p.exists(), f"one file of the pair left alone: {sorted(x.name for x in m.parent.iterdir())}"
    check_map_pair(m, p)
    assert {"map": _sha(m), "parquet": _sha(p)} == old, "a new pair was left by a failed run"
    return "old"


@pytest.mark.parametrize("where", ["build_table", "descriptor_arrow", "write_arrow", "sha256_file"])
def test_failed_descriptor_step_leaves_the_old_pair(two_runs: tuple[Path, Path], tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch, where: str) -> None:
    """The descriptor step fails while an earlier MAP.mcap/MAP.parquet pair is in place: before
    the map was finished (building the table), after the map was finished under its temporary
    name (hashing it), or while the Parquet was half written: the old pair is untouched."""
    m, p, old = _old_pair(two_runs, tmp_path)
    module = map_step if where == "build_table" else artefact
    real = getattr(module, where)

    def failing(*args: object, **kw: object) -> object:
        if where == "write_arrow":
            real(*args, **kw)  # the Parquet is complete under its temporary name, then the step fails
        raise OSError(28, f"no space left on device (test: {where})")

    monkeypatch.setattr(module, where, failing)
    with pytest.raises((OSError, DescriptorError), match=f"test: {where}"):
        make_map(DEMO, m, MapConfig(topics=(COMP,)))
    monkeypatch.setattr(module, where, real)
    assert _no_mismatched_pair(m, p, old) == "old"
    assert _leftovers(tmp_path) == []  # no temporary file left


def test_failed_run_without_an_old_pair_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def failing(*args: object, **kw: object) -> object:
        raise RuntimeError("describing failed (test)")

    monkeypatch.setattr(map_step, "build_table", failing)
    with pytest.raises(RuntimeError, match="describing failed"):
        make_map(DEMO, tmp_path / "MAP.mcap", MapConfig(topics=(COMP,), stride=2))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("fails,left", [("MAP.mcap", "old"), ("MAP.parquet", "neither")])
def test_failed_rename_never_leaves_a_mismatched_pair(two_runs: tuple[Path, Path], tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch, fails: str, left: str) -> None:
    """Both files are complete and the rename of one into place fails: the map's (the old Parquet
    is moved back: the old pair) or the Parquet's (the new map is removed: neither)."""
    m, p, old = _old_pair(two_runs, tmp_path)
    real = os.replace
    tried: list[str] = []

    def replace(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
        if Path(dst).name == fails and Path(src).name.endswith(".tmp"):
            tried.append(Path(src).name)
            raise OSError(5, f"input/output error (test: renaming to {fails})")
        real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(OSError, match="test: renaming"):
        make_map(DEMO, m, MapConfig(topics=(COMP,)))
    assert tried, "the rename under test was never tried"
    monkeypatch.setattr(os, "replace", real)
    assert _no_mismatched_pair(m, p, old) == left
    assert _leftovers(tmp_path) == []


def test_map_without_descriptors_removes_the_table_of_the_map_it_replaces(two_runs: tuple[Path, Path],
                                                                          tmp_path: Path) -> None:
    m, p, _old = _old_pair(two_runs, tmp_path)
    res = make_map(DEMO, m, MapConfig(topics=(COMP,), descriptor=None, stride=2))
    assert res.descriptors is None and m.exists() and not p.exists()
    assert _link(m) == {"scheme": "1", "descriptors_sha256": "", "descriptors_file": ""}
    shutil.copyfile(two_runs[1].with_suffix(".parquet"), p)  # a Parquet naming another map stays
    with pytest.raises(MapPairError, match=f"{p} does not belong to the map {m}: that map was written without"):
        check_map_pair(m, p)
    make_map(DEMO, m, MapConfig(topics=(COMP,), descriptor=None, stride=2))
    assert p.exists() and _recorded_map(p)[1] == "half.mcap"
    # a table of an earlier map of this name (that map itself already replaced) goes too
    t = pq.read_table(p)
    pq.write_table(t.replace_schema_metadata({**t.schema.metadata, b"memlog.map_file": b"MAP.mcap"}), p)
    make_map(DEMO, m, MapConfig(topics=(COMP,), descriptor=None, stride=2))
    assert not p.exists() and _leftovers(tmp_path) == []


def test_real_log_float16_pair_round_trip(tmp_path: Path) -> None:
    """The shared Stromovka drive (DINOv2 descriptors stored as float16), every 10th frame; and
    every 12th frame as another run of the same map name."""
    log = shared("stromovka_autumn.mcap")
    m = _map_cli(tmp_path, "MAP", "--stride", "10", "--descriptor-dtype", "float16", log=log)
    p = m.with_suffix(".parquet")
    assert pq.read_schema(p).metadata[b"memlog.dtype"] == b"float16"
    check_map_pair(m, p)
    first = (_sha(m), _sha(p))
    keep = tmp_path / "first.parquet"
    shutil.copyfile(p, keep)
    _map_cli(tmp_path, "MAP", "--stride", "12", "--descriptor-dtype", "float16", log=log)
    assert (_sha(m), _sha(p)) != first
    check_map_pair(m, p)
    with pytest.raises(MapPairError, match=f"{keep} does not belong to the map {m}"):
        check_map_pair(m, keep)


def test_batch_gets_the_same_guarantee(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``memlog batch`` writes its maps through the same step: its pairs check, and a log whose
    descriptor step fails keeps its earlier pair."""
    from memlog.steps.batch import BatchConfig, batch
    from tests.stand_in import use_stand_in

    use_stand_in(monkeypatch)
    logs = [FIXTURES / "ros2_mcap"]
    out = tmp_path / "out"
    first = batch(logs, out, BatchConfig(workers=1)).logs[0]
    assert first.status == "ok"
    m, p = Path(first.outputs["map"]), Path(first.outputs["descriptors"])
    check_map_pair(m, p)
    old = {"map": _sha(m), "parquet": _sha(p)}

    def failing(*args: object, **kw: object) -> object:
        raise OSError(28, "no space left on device (test)")

    monkeypatch.setattr(map_step, "build_table", failing)
    again = batch(logs, out, BatchConfig(workers=1, resume=False)).logs[0]
    assert again.status == "failed" and "no space left" in str(again.error)
    assert _no_mismatched_pair(m, p, old) == "old"
