#!/usr/bin/env python3
"""What a video camera topic costs to read: milliseconds per frame to stream and decode one
960x540 frame (``LogReader.frames`` + ``Frame.decode_bgr``, as every step reads frames) from H.264
(``foxglove.CompressedVideo``, a keyframe every 30 frames) against JPEG (``foxglove.CompressedImage``,
quality 90), with the log's size; also a window starting mid-stream (decoded from the keyframe
before it) and every 10th frame.

The frames are the shared Stromovka autumn drive's (1024x384), resized to 960x540, and encoded here
(``fixtures/video_logs.py``).

    python benchmarks/video_decode.py [--repeats 3]

Prints a Markdown table: log, frames read, ms per frame (median of the repeats), MB.
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))
SIZE = (960, 540)


def frames() -> tuple[list, list[int]]:
    import cv2

    from memlog.io.open import open_log

    imgs, stamps = [], []
    with open_log(SHARED / "stromovka_drive_autumn.mcap") as log:
        for f in log.frames():
            imgs.append(cv2.resize(f.decode_bgr(), SIZE, interpolation=cv2.INTER_AREA))
            stamps.append(f.log_time_ns)
    return imgs, stamps


def write_jpeg_log(path: Path, imgs: list, stamps: list[int]) -> None:
    import cv2
    from mcap.writer import Writer

    schema = {"type": "object", "properties": {"timestamp": {"type": "object"}, "frame_id": {"type": "string"},
                                               "data": {"type": "string"}, "format": {"type": "string"}}}
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        ch = w.register_channel("/camera/image", "json",
                                w.register_schema("foxglove.CompressedImage", "jsonschema", json.dumps(schema).encode()))
        for img, t in zip(imgs, stamps):
            data = bytes(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1])
            msg = {"timestamp": {"sec": t // 10**9, "nsec": t % 10**9}, "frame_id": "camera", "format": "jpeg",
                   "data": base64.b64encode(data).decode()}
            w.add_message(ch, log_time=t, publish_time=t, data=json.dumps(msg).encode())
        w.finish()


def read_ms(path: Path, repeats: int, **window: object) -> tuple[int, float]:
    """Frames read and the median ms per frame to stream and decode them."""
    from memlog.io.open import open_log

    times, n = [], 0
    for _ in range(repeats):
        t0 = time.perf_counter()
        n = 0
        with open_log(path) as log:
            for f in log.frames(**window):  # type: ignore[arg-type]
                f.decode_bgr()
                n += 1
        times.append((time.perf_counter() - t0) / max(n, 1) * 1e3)
    return n, statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    from fixtures.video_logs import encode, write_video_log

    imgs, stamps = frames()
    with tempfile.TemporaryDirectory() as tmp:
        jpeg, h264 = Path(tmp) / "jpeg.mcap", Path(tmp) / "h264.mcap"
        write_jpeg_log(jpeg, imgs, stamps)
        write_video_log(h264, encode(imgs, "h264", gop=30), stamps)
        mid = stamps[len(stamps) // 2 + 7]
        rows = []
        for name, path in (("JPEG q90 (foxglove.CompressedImage)", jpeg), ("H.264, keyframe every 30 (CompressedVideo)",
                                                                             h264)):
            mb = path.stat().st_size / 1e6
            for what, window in (("every frame", {}), ("second half, from mid-GOP", {"start_ns": mid}),
                                 ("every 10th frame", {"stride": 10})):
                n, ms = read_ms(path, args.repeats, **window)
                rows.append(f"| {name} | {what} | {n} | {ms:.2f} | {mb:.1f} |")
    print(f"{len(imgs)} frames of the Stromovka autumn drive at {SIZE[0]}x{SIZE[1]}; median of {args.repeats} "
          "reads\n")
    print("| log | frames read | n | ms per frame read | MB |")
    print("|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
