#!/usr/bin/env python3
"""Cost of memlog's score records per encoding family: bytes per message, microseconds to encode
one record (score/map writing) and to decode one back (``read_scores``).

    python benchmarks/record_codecs.py [N]      # N records per family (default 5000)

The records are typical: a selected frame with its 5x5 matrix (some crops unscored) and five stage
timings, and a frame rejected by staticity (no ES, no MS, no matrix), alternating.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def records(n: int) -> list[dict]:
    out = []
    for i in range(n):
        base = {"timestamp": {"sec": 1_700_000_000 + i, "nsec": 5_000_000}, "log_time": 1_700_000_000_005_000_000 + i,
                "topic": "/cam0/image_raw", "frame_index": i, "thresholds": {"mt": 0.5, "st": 0.6, "et": 0.4},
                "crops_surrogate": 0, "error": None}
        timing = {"decode": 1.234, "resize": 2.5, "staticity": 41.25, "entropy": 12.125, "memorability": 3980.5}
        if i % 2:
            out.append({**base, "ms": None, "ms_low": None, "ms_high": None, "ms_exact": True, "ss": 0.41, "es": None,
                        "memorability": None, "crops_scored": 0, "selected": False, "rejected_by": "staticity",
                        "detections": 3, "timing_ms": {k: timing[k] for k in ("decode", "resize", "staticity")}})
        else:
            m = [[round(0.5 + (r * 5 + c) / 100, 6) if (r + c) % 4 else None for c in range(5)] for r in range(5)]
            out.append({**base, "ms": 0.612345, "ms_low": 0.6, "ms_high": 0.63, "ms_exact": False, "ss": 0.97,
                        "es": 0.55, "memorability": m, "crops_scored": 19, "selected": True, "rejected_by": None,
                        "detections": 0, "timing_ms": timing})
    return out


def main(argv: list[str]) -> int:
    from memlog.io import open_log
    from memlog.io.mcap import McapLogWriter
    from memlog.outputs.channels import SCORES, MemlogChannels, decode_record

    n = int(argv[0]) if argv else 5000
    recs = records(n)
    print(f"{n} score records per family (alternating selected / rejected by staticity)\n")
    print("| family | bytes / message | encode µs / record | decode µs / record |")
    print("|---|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as tmp:
        for family in ("json", "ros2", "ros1", "protobuf"):
            path = Path(tmp) / f"{family}.mcap"
            with McapLogWriter(path, profile=family if family.startswith("ros") else "", compression="none") as w:
                out = MemlogChannels(w, family)
                cid = out.add("/cam0/image_raw/memlog/scores", SCORES)
                out.write(cid, 0, recs[0])  # codec set-up (type stores, descriptors) outside the timing
                t0 = time.perf_counter()
                for i, rec in enumerate(recs):
                    out.write(cid, i + 1, rec)
                enc = (time.perf_counter() - t0) / n * 1e6
            with open_log(path) as log:
                msgs = list(log.messages())
            size = sum(len(m.data) for m in msgs[1:]) / n
            decode_record(SCORES, msgs[0].channel, msgs[0].data)
            t0 = time.perf_counter()
            got = [decode_record(SCORES, m.channel, m.data) for m in msgs[1:]]
            dec = (time.perf_counter() - t0) / n * 1e6
            assert got == recs, family
            print(f"| {family} | {size:.0f} | {enc:.1f} | {dec:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
