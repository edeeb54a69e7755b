#!/usr/bin/env python3
"""Make ``docs/report.png``: a screenshot of the HTML report of ``memlog evaluate``.

The report is built on the bundled fixtures, whose pictures may be redistributed (scikit-image's
sample photographs, see ``fixtures/make_fixtures.py``): the reference drive is ``demo.mcap``'s
JPEG topic, the query its raw topic, the truth the two drives' GNSS positions within 6 m. The logs
are copied into a work directory and evaluated from there under relative paths, so the report (and
the picture) names no path of this machine. Headless Chromium renders the page in a tall window;
the white below the page is trimmed.

Usage (needs memlog installed with its models, ``memlog models prepare``, and ``chromium``)::

    python docs/make_report_screenshot.py                 # writes docs/report.png
    python docs/make_report_screenshot.py --work /tmp/w   # keep the run (a second run reuses its scores)

Scoring the eight frames takes a few seconds to minutes, depending on the machine.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DEMO = ROOT / "fixtures" / "demo.mcap"
REFERENCE_TOPIC = "/camera/image/compressed"
QUERY_TOPIC = "/camera/image_raw"


def evaluate(work: Path) -> Path:
    """Run ``memlog evaluate`` on the fixture pair in ``work``; returns the report's path."""
    logs = work / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    if not (logs / DEMO.name).is_file():
        shutil.copyfile(DEMO, logs / DEMO.name)
    log = f"logs/{DEMO.name}"
    cmd = [sys.executable, "-m", "memlog", "evaluate", "--reference", log, "--query", log,
           "--reference-topic", REFERENCE_TOPIC, "--query-topic", QUERY_TOPIC, "--tolerance", "6",
           "--seeds", "5", "-o", "evaluation", "-q"]
    subprocess.run(cmd, cwd=work, check=True)
    return work / "evaluation" / "report.html"


def screenshot(report: Path, png: Path, width: int, height: int, browser: str) -> None:
    """Render ``report`` in headless Chromium (``width`` x ``height``), trim the white below the
    page and write ``png``."""
    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp) / "raw.png"
        subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                        f"--user-data-dir={Path(tmp) / 'profile'}", f"--window-size={width},{height}",
                        f"--screenshot={raw}", report.resolve().as_uri()],
                       check=True, capture_output=True, timeout=300)
        img = cv2.imread(str(raw))
    if img is None:
        raise SystemExit(f"chromium wrote no screenshot of {report}")
    inked = np.flatnonzero((img < 245).any(axis=(1, 2)))
    bottom = min(img.shape[0], int(inked.max()) + 30) if inked.size else img.shape[0]
    if bottom >= img.shape[0] - 30:
        print(f"note: the page is taller than {height} px; cut at the window (--height to see more)", file=sys.stderr)
    png.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(png), img[:bottom], [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise SystemExit(f"cannot write {png}")
    print(f"wrote {png} ({width}x{bottom})")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "report.png", help="the PNG (default docs/report.png)")
    ap.add_argument("--work", type=Path, help="work directory to keep (default: a temporary one)")
    ap.add_argument("--width", type=int, default=1400, help="window width in pixels (default 1400)")
    ap.add_argument("--height", type=int, default=9000, help="window height in pixels: taller than the page "
                                                              "(default 9000)")
    ap.add_argument("--chromium", default=shutil.which("chromium") or shutil.which("chromium-browser"),
                    help="the browser (default: chromium on PATH)")
    args = ap.parse_args()
    if not args.chromium:
        raise SystemExit("chromium is missing (Debian: apt-get install chromium)")
    if args.work is not None:
        args.work.mkdir(parents=True, exist_ok=True)
        screenshot(evaluate(args.work), args.out, args.width, args.height, args.chromium)
        return 0
    with tempfile.TemporaryDirectory(prefix="memlog-report-") as tmp:
        screenshot(evaluate(Path(tmp)), args.out, args.width, args.height, args.chromium)
    return 0


if __name__ == "__main__":
    sys.exit(main())
