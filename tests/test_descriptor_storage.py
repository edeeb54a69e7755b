"""Tests of the descriptor table's Parquet storage: the streaming float32 read against a plain
Arrow read, files of the earlier layout, float16 storage (round trip, metadata, refusals)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from memlog.descriptors.base import DescriptorMeta
from memlog.descriptors.table import DescriptorTable
from memlog.errors import DescriptorError
from memlog.outputs import descriptor_table as dtab
from memlog.outputs.descriptor_table import read_descriptors, stored_dtype, write_descriptors


def _table(n: int = 50, dim: int = 24, seed: int = 0) -> DescriptorTable:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, dim)).astype(np.float32)
    topics = np.array(["/cam/a", "/cam/b", "/cam/c"])[rng.integers(0, 3, n)].tolist()
    return DescriptorTable(
        topic=topics, frame_index=np.arange(n) * 3, log_time_ns=np.arange(n) * 10**8 + 7,
        stamp_ns=np.arange(n) * 10**8, descriptors=x / np.linalg.norm(x, axis=1, keepdims=True),
        meta=DescriptorMeta("thumbnail", "1", dim, None, {"width": dim, "height": 1, "patch": 1}),
        ms=np.where(rng.random(n) < 0.2, np.nan, rng.random(n)), positions={"x": rng.normal(size=n)},
        extra={"source": "test"},
    )


def _plain_read(path: Path) -> dict[str, object]:
    """The file read the simple way: the whole table, Python lists, no streaming."""
    t = pq.read_table(path).to_pydict()
    return {"descriptors": np.array(t["descriptor"], dtype=np.float32), "topic": t["topic"],
            "frame_index": np.array(t["frame_index"]), "ms": np.array(t["ms"], dtype=np.float64)}


def _assert_same(back: DescriptorTable, plain: dict[str, object]) -> None:
    np.testing.assert_array_equal(back.descriptors, plain["descriptors"])
    assert back.descriptors.dtype == np.float32 and back.descriptors.flags.c_contiguous
    assert back.topic == plain["topic"] and all(type(t) is str for t in back.topic)
    np.testing.assert_array_equal(back.frame_index, plain["frame_index"])
    np.testing.assert_array_equal(back.ms, plain["ms"])  # None -> NaN on both sides


@pytest.mark.parametrize("row_group_bytes", [1 << 24, 24 * 4 * 7])  # one row group; groups of 7 rows
def test_streaming_read_equals_plain_read(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                          row_group_bytes: int) -> None:
    monkeypatch.setattr(dtab, "ROW_GROUP_BYTES", row_group_bytes)  # also the read batch size
    t = _table()
    path = write_descriptors(tmp_path / "m.parquet", t)
    assert pq.ParquetFile(path).metadata.num_row_groups == (1 if row_group_bytes > 1e6 else 8)
    back = read_descriptors(path)
    _assert_same(back, _plain_read(path))
    np.testing.assert_array_equal(back.descriptors, t.descriptors)
    assert back.topic == t.topic and back.extra == t.extra
    np.testing.assert_array_equal(back.positions["x"], t.positions["x"])


def test_reads_files_of_the_earlier_layout(tmp_path: Path) -> None:
    """Earlier files: nullable list of nullable floats, dictionary pages, one row group, no dtype key."""
    t = _table()
    path = write_descriptors(tmp_path / "new.parquet", t)
    new = pq.read_table(path)
    md = {k: v for k, v in new.schema.metadata.items() if k != b"memlog.dtype"}
    flat = pa.array(t.descriptors.reshape(-1), type=pa.float32())
    cols = {name: new.column(name) for name in new.column_names}
    cols["descriptor"] = pa.FixedSizeListArray.from_arrays(flat, t.descriptors.shape[1])
    old = pa.table(cols).replace_schema_metadata(md)
    pq.write_table(old, tmp_path / "old.parquet", compression="zstd")  # the earlier writer's call
    back = read_descriptors(tmp_path / "old.parquet")
    _assert_same(back, _plain_read(tmp_path / "old.parquet"))
    np.testing.assert_array_equal(back.descriptors, t.descriptors)
    assert stored_dtype(tmp_path / "old.parquet") == "float32"


def test_moving_index_round_trip_and_files_without_it(tmp_path: Path) -> None:
    """``moving_index`` is stored as a non-null int64 column and read back as written; a file
    without the column (written before it) reads with ``moving_index`` None, and a cache of it
    is not reused (it would match along the frame index)."""
    from dataclasses import replace

    t = _table()
    mi = t.frame_index - np.repeat(np.arange(10) * 3, 5)  # stops left out: a made-up but valid series
    path = write_descriptors(tmp_path / "m.parquet", replace(t, moving_index=mi))
    f = pq.read_table(path)
    assert f.schema.field("moving_index").type == pa.int64() and not f.schema.field("moving_index").nullable
    assert f.column("moving_index").to_pylist() == mi.tolist()
    back = read_descriptors(path)
    assert back.moving_index is not None and back.moving_index.dtype == np.int64
    np.testing.assert_array_equal(back.moving_index, mi)
    old = write_descriptors(tmp_path / "old.parquet", t)
    assert "moving_index" not in pq.read_table(old).column_names
    assert read_descriptors(old).moving_index is None
    with pytest.raises(DescriptorError, match="moving_index"):
        replace(t, moving_index=mi[:-1])


def test_float16_round_trip(tmp_path: Path) -> None:
    t = _table(n=40, dim=64)
    t.descriptors[0, :3] = [1e-6, -3e-5, 0.0]  # below float16's normal range
    p32 = write_descriptors(tmp_path / "m32.parquet", t)
    p16 = write_descriptors(tmp_path / "m16.parquet", t, dtype="float16")
    back = read_descriptors(p16)
    assert back.descriptors.dtype == np.float32
    # float16: 11 significant bits (relative error <= 2^-11); subnormals are spaced 2^-24 apart
    err = np.abs(back.descriptors - t.descriptors)
    assert np.all(err <= np.abs(t.descriptors) * 2.0**-11 + 2.0**-25)
    assert 0 < err.max()  # it really was stored in 16 bits
    np.testing.assert_array_equal(back.descriptors, t.descriptors.astype(np.float16).astype(np.float32))
    assert back.topic == t.topic and back.meta == t.meta
    assert stored_dtype(p16) == "float16" and stored_dtype(p32) == "float32"
    schema = pq.read_schema(p16)
    assert schema.metadata[b"memlog.dtype"] == b"float16"
    assert schema.field("descriptor").type.value_type == pa.float16()
    assert p16.stat().st_size < 0.75 * p32.stat().st_size


def test_float16_refused_out_of_range_and_unknown_dtype(tmp_path: Path) -> None:
    t = _table(n=5, dim=4)
    big = DescriptorTable(topic=t.topic, frame_index=t.frame_index, log_time_ns=t.log_time_ns, stamp_ns=t.stamp_ns,
                          descriptors=t.descriptors * 1e5, meta=t.meta)
    with pytest.raises(DescriptorError, match="float16's range"):
        write_descriptors(tmp_path / "big.parquet", big, dtype="float16")
    write_descriptors(tmp_path / "big32.parquet", big)  # float32 keeps it
    with pytest.raises(DescriptorError, match="float32 or float16|one of float32, float16"):
        write_descriptors(tmp_path / "x.parquet", t, dtype="float64")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big32.parquet"]  # nothing half-written


def test_metadata_and_column_must_agree(tmp_path: Path) -> None:
    t = _table(n=6, dim=4)
    p16 = write_descriptors(tmp_path / "m16.parquet", t, dtype="float16")
    raw = pq.read_table(p16)
    lying = raw.replace_schema_metadata({**raw.schema.metadata, b"memlog.dtype": b"float32"})
    pq.write_table(lying, tmp_path / "lying.parquet")
    for fn in (read_descriptors, stored_dtype):
        with pytest.raises(DescriptorError, match="metadata says the descriptors are float32 but the column holds "
                                                  "float16"):
            fn(tmp_path / "lying.parquet")
    doubles = raw.set_column(raw.column_names.index("descriptor"), "descriptor",
                             pa.FixedSizeListArray.from_arrays(pa.array(np.zeros(24)), 4))
    pq.write_table(doubles.replace_schema_metadata(raw.schema.metadata), tmp_path / "f64.parquet")
    with pytest.raises(DescriptorError, match="expected float32 or float16"):
        read_descriptors(tmp_path / "f64.parquet")


def test_null_descriptors_refused(tmp_path: Path) -> None:
    t = _table(n=6, dim=4)
    raw = pq.read_table(write_descriptors(tmp_path / "m.parquet", t))
    flat = pa.array(t.descriptors.reshape(-1), type=pa.float32())
    with_null = pa.FixedSizeListArray.from_arrays(flat, 4, mask=pa.array([False, True, False, False, False, False]))
    bad = raw.set_column(raw.column_names.index("descriptor"), "descriptor", with_null)
    pq.write_table(bad.replace_schema_metadata(raw.schema.metadata), tmp_path / "null.parquet")
    with pytest.raises(DescriptorError, match="1 descriptor\\(s\\) are null"):
        read_descriptors(tmp_path / "null.parquet")
    values = flat.to_pylist()
    values[5] = None
    holes = pa.FixedSizeListArray.from_arrays(pa.array(values, type=pa.float32()), 4)
    bad = raw.set_column(raw.column_names.index("descriptor"), "descriptor", holes)
    pq.write_table(bad.replace_schema_metadata(raw.schema.metadata), tmp_path / "hole.parquet")
    with pytest.raises(DescriptorError, match="null value"):
        read_descriptors(tmp_path / "hole.parquet")


def test_map_descriptor_dtype_option(tmp_path: Path) -> None:
    from memlog.cli.app import build_parser
    from memlog.cli.commands import map_config
    from memlog.errors import ConfigError
    from memlog.steps.map import MapConfig

    args = build_parser().parse_args(["map", "log.mcap", "-o", str(tmp_path / "m.mcap"), "--descriptor-dtype", "float16"])
    assert map_config(args).descriptor_dtype == "float16"
    assert map_config(build_parser().parse_args(["map", "log.mcap", "-o", "m.mcap"])).descriptor_dtype == "float32"
    conf = tmp_path / "memlog.toml"
    conf.write_text('[map]\ndescriptor_dtype = "float16"\n')
    args = build_parser().parse_args(["map", "log.mcap", "-o", "m.mcap", "--config", str(conf)])
    assert map_config(args).descriptor_dtype == "float16"
    with pytest.raises(ConfigError, match="descriptor_dtype"):
        MapConfig(descriptor_dtype="float64")  # type: ignore[arg-type]
