"""memlog's outputs on the shared logs, read back into plain values, and recorded.

The restructuring of issue 41 (the matcher package, flags generated from the configs, the runtime
context) must not change what memlog writes. :func:`run_all` runs the main commands through the CLI
(``python -m memlog``, as users run them) on the shared logs and reads every output back
(:func:`summarise`): image messages by their bytes' sha256, memlog's own records and metadata decoded,
the timing fields left out (:data:`TIMING`, the only fields allowed to differ between runs). Long
float arrays (descriptors, patch features) are kept as their length, sum, sum of squares and first
values, so that the recorded file stays small.

``python -m tests.recorded_outputs`` writes ``tests/data/recorded_outputs.json.gz`` (the recording of
the code before the change); ``tests/test_recorded_outputs.py`` runs the commands again and compares
with :func:`differences`: strings, integers and structure exactly, floats within a relative 1e-4 (the
last bits of ONNX Runtime's and BLAS's sums may differ from one CPU to another).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
DATA = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))
RECORDED = Path(__file__).resolve().parent / "data" / "recorded_outputs.json.gz"

#: Keys whose values are times measured by the run (left out wherever they occur).
TIMING = frozenset({
    "seconds", "mean_ms_per_frame", "timing_ms", "seconds_per_query", "match_seconds_per_query", "ms_per_query",
    "timing", "timing_map", "search_timing",
})
#: Keys that hold the size or hash of a file that holds timing fields, or an input file's modification
#: time (which a copy of the shared data changes).
PLACES = frozenset({"descriptors_sha256", "map_sha256", "memlog.map_sha256", "bytes_out", "byte_fraction",
                    "mtime_ns"})

#: The commands: name -> argument list (``{D}`` the shared data folder, paths relative to the run's folder).
COMMANDS: dict[str, list[str]] = {
    "score": ["score", "{D}/euroc_micro_foxglove.mcap", "-o", "scored.mcap", "--stride", "5"],
    "map": ["map", "{D}/stromovka_drive_autumn.mcap", "-o", "map.mcap"],
    "localize": ["localize", "map.parquet", "{D}/stromovka_drive_winter.mcap", "-o", "matches.parquet",
                 "--map", "map.mcap", "-k", "2"],
    "map_nordland": ["map", "{D}/nordland_dev_summer.mcap", "-o", "nordland.mcap", "--keep-fraction", "0.5"],
    "localize_nordland": ["localize", "nordland.parquet", "{D}/nordland_dev_winter.mcap", "-o", "nordland.csv",
                          "-k", "1"],
    "evaluate": ["evaluate", "--reference", "{D}/stromovka_drive_autumn.mcap", "--query",
                 "{D}/stromovka_drive_winter.mcap", "--truth", "{D}/stromovka_drive_truth.json", "-o", "evaluate",
                 "--seeds", "2", "--no-report"],
}


def _floats(xs: list[float]) -> dict[str, Any]:
    return {"n": len(xs), "abs_sum": math.fsum(abs(x) for x in xs), "sumsq": math.fsum(x * x for x in xs),
            "head": xs[:4]}


def _array(text: str) -> Any:
    """A long base64 string (memlog stores float32 matrices so) as :func:`_floats`, else its sha256."""
    import base64
    import binascii

    import numpy as np

    try:
        raw = base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        return "sha256:" + hashlib.sha256(text.encode()).hexdigest()
    if len(raw) % 4:
        return "sha256:" + hashlib.sha256(raw).hexdigest()
    with np.errstate(all="ignore"):
        return _floats(np.frombuffer(raw, "<f4").astype(float).tolist())


def _plain(value: Any) -> Any:
    """JSON-like ``value`` without timing fields; JSON strings decoded; long float lists and
    base64 arrays summarised."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items() if str(k) not in TIMING and str(k) not in PLACES}
    if isinstance(value, (list, tuple)):
        if len(value) > 16 and all(isinstance(v, float) for v in value):
            return _floats([float(v) for v in value])
        return [_plain(v) for v in value]
    if isinstance(value, (bytes, bytearray, memoryview)):
        return "sha256:" + hashlib.sha256(bytes(value)).hexdigest()
    if isinstance(value, str) and value[:1] in "[{":
        try:
            return _plain(json.loads(value))
        except ValueError:
            return value
    if isinstance(value, str) and len(value) > 500:
        return _array(value)
    if hasattr(value, "tolist"):  # numpy values
        return _plain(value.tolist())
    return value


def summarise_mcap(path: Path) -> dict[str, Any]:
    """Every record of an MCAP memlog wrote: messages of memlog's channels decoded (JSON) or by their
    bytes' sha256 (images), the score records decoded, the metadata."""
    from mcap.reader import make_reader

    from memlog.outputs.annotated import read_scores

    msgs = []
    with open(path, "rb") as fh:
        r = make_reader(fh, validate_crcs=True)
        for _, ch, m in r.iter_messages(log_time_order=False):
            if ch.topic.endswith("/memlog/scores"):
                continue
            body: Any = bytes(m.data)
            if ch.message_encoding == "json" and "/memlog/" in ch.topic:
                body = json.loads(body)
            msgs.append([ch.topic, m.log_time, m.publish_time, m.sequence, _plain(body)])
        meta = {md.name: _plain(dict(md.metadata)) for md in r.iter_metadata()}
    return {"messages": msgs, "scores": _plain(read_scores(path)), "metadata": meta}


def _number(text: str) -> Any:
    try:
        return int(text)
    except ValueError:
        try:
            return float(text)
        except ValueError:
            return text


def summarise_table(path: Path) -> dict[str, Any]:
    """A Parquet or CSV table memlog wrote: its rows and its metadata."""
    if path.suffix == ".csv":
        import csv

        with open(path, newline="") as fh:
            return {"rows": [[_number(c) for c in row] for row in csv.reader(fh)]}
    import pyarrow.parquet as pq

    t = pq.read_table(path)
    meta = {k.decode(): v.decode() for k, v in (t.schema.metadata or {}).items()}
    return {"rows": _plain(t.replace_schema_metadata(None).to_pylist()), "metadata": _plain(meta)}


def summarise(out: Path) -> dict[str, Any]:
    """Every output of :data:`COMMANDS` in ``out``, read back."""
    res: dict[str, Any] = {}
    for name in ("scored.mcap", "map.mcap", "nordland.mcap"):
        res[name] = summarise_mcap(out / name)
    for name in ("map.parquet", "matches.parquet", "nordland.parquet", "nordland.csv"):
        res[name] = summarise_table(out / name)
    for name in sorted(p.name for p in (out / "evaluate").glob("*.json")):
        res[f"evaluate/{name}"] = _plain(json.loads((out / "evaluate" / name).read_text()))
    text = json.dumps(res).replace(str(out.resolve()), "<out>").replace(str(DATA.resolve()), "<data>")
    return json.loads(text.replace(str(DATA), "<data>"))


def run_all(out: Path, summary: bool = True) -> dict[str, Any]:
    """Run :data:`COMMANDS` in ``out`` through the CLI and read back what they wrote (``summary``
    False: run them only, and return nothing)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for name, argv in COMMANDS.items():
        cmd = [sys.executable, "-m", "memlog", *(a.replace("{D}", str(DATA)) for a in argv)]
        proc = subprocess.run(cmd, cwd=out, env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"{name}: exit {proc.returncode}\n{proc.stderr[-3000:]}")
    return summarise(out) if summary else {}


def recorded() -> Any:
    """The recording made by ``python -m tests.recorded_outputs``."""
    import gzip

    with gzip.open(RECORDED, "rt", encoding="utf-8") as fh:
        return json.load(fh)


#: Hashes of a float fit (the whitening, the patch PCA): the bits of an SVD, which the same code gives
#: differently on another CPU (its BLAS kernels). Compared as hashes only (64 hex digits); what the fit
#: does is compared through the descriptors' floats and the metrics, within ``rel``.
FIT_HASH = re.compile(r"(whitening/sha256|whitening_sha256|patch_pca/sha256|/patch_pca)$")
_HEX64 = re.compile(r"[0-9a-f]{64}")


def differences(recorded: Any, now: Any, where: str = "", rel: float = 1e-4) -> list[str]:
    """Where ``now`` differs from ``recorded``: structure, strings and integers exactly (a float fit's
    hash, :data:`FIT_HASH`, as a hash), floats within ``rel`` (and 1e-6 absolute)."""
    if FIT_HASH.search(where) and all(isinstance(v, str) and _HEX64.fullmatch(v) for v in (recorded, now)):
        return []
    if isinstance(recorded, dict) and isinstance(now, dict):
        out = [f"{where}: key {k!r} {'gone' if k in recorded else 'new'}" for k in sorted(set(recorded) ^ set(now))]
        for k in sorted(set(recorded) & set(now)):
            out += differences(recorded[k], now[k], f"{where}/{k}", rel)
        return out
    if isinstance(recorded, list) and isinstance(now, list):
        if len(recorded) != len(now):
            return [f"{where}: {len(recorded)} items recorded, {len(now)} now"]
        out = []
        for i, (a, b) in enumerate(zip(recorded, now)):
            out += differences(a, b, f"{where}[{i}]", rel)
        return out
    if isinstance(recorded, float) or isinstance(now, float):
        if isinstance(recorded, (int, float)) and isinstance(now, (int, float)) and not isinstance(recorded, bool):
            if math.isclose(recorded, now, rel_tol=rel, abs_tol=1e-6) or (math.isnan(recorded) and math.isnan(now)):
                return []
    elif recorded == now and type(recorded) is type(now):
        return []
    return [f"{where}: recorded {recorded!r}, now {now!r}"]


if __name__ == "__main__":  # record
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        summary = run_all(Path(tmp))
    RECORDED.parent.mkdir(exist_ok=True)
    import gzip

    with gzip.open(RECORDED, "wt", encoding="utf-8", compresslevel=9) as fh:  # type: ignore[assignment]
        fh.write(json.dumps(summary, sort_keys=True, separators=(",", ":")) + "\n")
    print(f"wrote {RECORDED} ({RECORDED.stat().st_size} bytes)")
