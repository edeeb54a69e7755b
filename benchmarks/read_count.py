#!/usr/bin/env python3
"""How many times a damaged or unfinished log is read by one job: bytes read from the log over its
size, and how many times it is opened, for ``memlog map``, ``map --workers 2`` and ``batch``.

    python benchmarks/read_count.py [--log PATH] [--work DIR] [--commands map,map-w2,batch]

Two copies of the log (default: the shared Stromovka autumn drive, 1024x384 JPEG in an indexed,
chunked MCAP) are made in ``--work``:

* ``crc``: one chunk in the middle has a flipped byte in its data (its CRC no longer matches), the
  summary and index intact;
* ``cut``: the file cut at 85 % of its bytes, as a recording that was never finished (no summary,
  no index).

Each command runs on a fresh copy of its case (a file no run has seen: no scan record of it is
kept yet), under ``strace -f -y`` (every process and thread it starts, workers included); the
table sums the bytes that ``read``/``pread64``/``readv``/``preadv`` calls returned from that
file, and counts its ``open``/``openat`` calls; beside them, the bytes the job wrote to its spool
(``<cache>/spool/``, :mod:`memlog.io.spool`: the chunks it read, kept for its later passes) and
read back from it. A file read once in full gives 1.0x; the
checks of issue 39 ask for at most 2.0x with ``--workers 2`` and in ``batch``. The commands run
with the defaults otherwise (``map -o``, ``batch -o``); timings under strace mean nothing and are
not printed; ``batch`` scores with ``--fast`` (the int8 surrogate: exact ResMem would take ten minutes a
run on two cores and reads the log the same way). Needs ``strace`` (Debian's package).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))
COMMANDS = ("map", "map-w2", "batch")

_READ = re.compile(r"\b(?:read|pread64|readv|preadv|preadv2)\((\d+)<([^>]*)>.*\)\s+=\s+(\d+)")
_WRITE = re.compile(r"\b(?:write|pwrite64|writev|pwritev|pwritev2)\((\d+)<([^>]*)>.*\)\s+=\s+(\d+)")
_OPEN = re.compile(r"\bopen(?:at)?\(.*?\"([^\"]+)\".*\)\s+=\s+(\d+)")


def damaged_copies(log: Path, work: Path) -> dict[str, Path]:
    """``crc`` and ``cut`` copies of ``log`` (an indexed, chunked MCAP) in ``work``."""
    from mcap.reader import make_reader

    with open(log, "rb") as fh:
        summary = make_reader(fh).get_summary()
    if summary is None or not summary.chunk_indexes:
        raise SystemExit(f"{log}: not an indexed, chunked MCAP (the crc case needs its chunk index)")
    data = bytearray(log.read_bytes())
    ci = summary.chunk_indexes[len(summary.chunk_indexes) // 2]
    at = ci.chunk_start_offset + ci.chunk_length - ci.compressed_size // 2  # inside the chunk's records
    data[at] ^= 0xFF
    out = {"crc": work / "crc.mcap", "cut": work / "cut.mcap"}
    out["crc"].write_bytes(bytes(data))
    out["cut"].write_bytes(log.read_bytes()[: int(log.stat().st_size * 0.85)])
    return out


def measure(argv: list[str], log: Path, trace: Path, env: dict[str, str] | None = None) -> tuple[int, int, int, int]:
    """(bytes read from ``log``, opens of it, bytes written to and read from the job's spool
    (:mod:`memlog.io.spool`)) by ``argv`` and every process it starts."""
    for old in trace.parent.glob(trace.name + ".*"):
        old.unlink()
    # -ff: one file per thread, so that no call is split into "unfinished ... resumed" lines
    cmd = ["strace", "-ff", "-y", "-qq", "-s", "0", "-e",
           "trace=openat,open,read,pread64,readv,preadv,preadv2,write,pwrite64,writev,pwritev,pwritev2",
           "-o", str(trace), *argv]
    res = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
                         cwd=trace.parent)  # (not a checkout: python -m puts the working directory first)
    if res.returncode not in (0, 3):  # 3: damage reported, what these logs must give
        raise SystemExit(f"{' '.join(argv)} exited {res.returncode}:\n{res.stderr[-2000:]}")
    real = os.path.realpath(log)
    got = opens = spool_in = spool_out = 0
    for part in sorted(trace.parent.glob(trace.name + ".*")):
        got, opens, spool_in, spool_out = _count(part, real, (got, opens, spool_in, spool_out))
    return got, opens, spool_in, spool_out


def _count(part: Path, real: str, sums: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    """``sums`` (see :func:`measure`) plus what one thread's trace file ``part`` adds."""
    got, opens, spool_in, spool_out = sums
    with open(part, errors="replace") as fh:
        for line in fh:
            m = _READ.search(line)
            if m and m.group(2) == real:
                got += int(m.group(3))
                continue
            if m and "/spool/" in m.group(2):
                spool_out += int(m.group(3))
                continue
            m = _WRITE.search(line)
            if m and "/spool/" in m.group(2):
                spool_in += int(m.group(3))
                continue
            m = _OPEN.search(line)
            if m and os.path.realpath(m.group(1)) == real:
                opens += 1
    return got, opens, spool_in, spool_out


def command(name: str, log: Path, out: Path) -> list[str]:
    memlog = [sys.executable, "-m", "memlog", "-q"]
    if name == "map":
        return [*memlog, "map", str(log), "-o", str(out / "map.mcap")]
    if name == "map-w2":
        return [*memlog, "map", str(log), "-o", str(out / "map.mcap"), "--workers", "2"]
    if name == "batch":
        return [*memlog, "batch", str(log), "-o", str(out), "--workers", "2", "--fast"]
    raise SystemExit(f"unknown command {name!r} (one of {', '.join(COMMANDS)})")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    ap.add_argument("--log", type=Path, default=SHARED / "stromovka_autumn.mcap")
    ap.add_argument("--work", type=Path, default=None, help="folder for the copies and outputs (default: a temp dir)")
    ap.add_argument("--commands", default=",".join(COMMANDS))
    ap.add_argument("--pythonpath", default=None,
                    help="run the memlog found here (another checkout, to compare commits on one host)")
    args = ap.parse_args(argv)
    if shutil.which("strace") is None:
        raise SystemExit("strace not found (Debian: apt-get install strace)")
    if not args.log.is_file():
        raise SystemExit(f"{args.log}: no such log (the shared data, or --log)")
    names = [c for c in args.commands.split(",") if c]
    work = args.work or Path(tempfile.mkdtemp(prefix="memlog-reads-"))
    work.mkdir(parents=True, exist_ok=True)
    copies = damaged_copies(args.log, work)
    print(f"log: {args.log.name}, {args.log.stat().st_size / 1e6:.1f} MB\n")
    print("| case | command | file MB | read MB | reads of the file | opens | spool written MB | spool read MB |")
    print("|---|---|---|---|---|---|---|---|")
    for case, path in copies.items():
        size = path.stat().st_size
        for name in names:
            out = work / f"{case}-{name}"
            shutil.rmtree(out, ignore_errors=True)
            out.mkdir()
            fresh = out / path.name  # a file no run has seen (nothing learned of it is kept yet)
            shutil.copyfile(path, fresh)
            env = None if args.pythonpath is None else dict(os.environ, PYTHONPATH=args.pythonpath)
            got, opens, s_in, s_out = measure(command(name, fresh, out), fresh, work / f"{case}-{name}.strace", env)
            fresh.unlink()
            print(f"| {case} | {name} | {size / 1e6:.1f} | {got / 1e6:.1f} | {got / size:.2f}x | {opens} | "
                  f"{s_in / 1e6:.1f} | {s_out / 1e6:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
