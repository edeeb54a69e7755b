#!/usr/bin/env python3
"""The damage sweep: a few hundred damaged or wrong copies of the fixture and shared logs.

    python benchmarks/damage_sweep.py [--seed 1] [--trunc 12] [--flip 16] [--limit 120] [--fixtures-only] [-v]

Every case (truncations at many offsets, flipped bytes, summary/index damage, broken ROS 2 bag
metadata, wrong row values, garbage images and decompression bombs, absurd sizes) is built in a
temporary directory and run through the frame stream (with pixel decoding), ``memlog inspect``
and ``memlog convert`` in this process, each under a time limit (``--limit`` seconds). A case
fails on a traceback or internal error, a hang, a modified input, a temporary or partial file
left behind, a converted log that holds other messages than the reader returned, a readable
message lost (the survivors are computed from the intact log by ``tests/damage_kit.py``, with
mcap's own reader, rosbags and sqlite row lookups) or, for logs with checksums, damage read as
data or called clean. Prints a Markdown table: cases per damage kind and outcome, then the
failures and the cost of the 32 MiB zero-filled tails. Exit status 1 when a case failed.
"""

from __future__ import annotations

import argparse
import random
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.conftest import FIXTURES, SHARED  # noqa: E402
from tests.damage_kit import Case, image_cases, mcap_cases, ros1_cases, ros2_cases, run_case  # noqa: E402


def build_cases(seed: int, n_trunc: int, n_flip: int, fixtures_only: bool) -> list[Case]:
    rng = random.Random(seed)
    cases: list[Case] = []
    for name in ("demo.mcap", "foxglove_json.mcap", "foxglove_proto.mcap", "encodings.mcap"):
        cases += mcap_cases(FIXTURES / name, rng, n_trunc // 2, n_flip // 2)
    cases += ros1_cases(FIXTURES / "ros1.bag", rng, n_trunc, n_flip)
    cases += ros2_cases(FIXTURES / "ros2_sqlite", rng, n_trunc // 2, n_flip // 2)
    cases += ros2_cases(FIXTURES / "ros2_mcap", rng, n_trunc // 2, n_flip // 2)
    cases += image_cases(FIXTURES)
    if not fixtures_only and SHARED.exists():
        for name in ("euroc_micro_ros2.mcap", "euroc_micro_foxglove.mcap", "nordland_dev_summer.mcap"):
            cases += mcap_cases(SHARED / name, rng, n_trunc, n_flip)
        cases += ros1_cases(SHARED / "euroc_micro_ros1.bag", rng, n_trunc, n_flip)
        cases += ros2_cases(SHARED / "euroc_micro_ros2_db3", rng, n_trunc, n_flip)
    return cases


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--trunc", type=int, default=12, help="random truncation offsets per log")
    ap.add_argument("--flip", type=int, default=16, help="random flipped bytes per log")
    ap.add_argument("--limit", type=int, default=120, help="seconds a case may take before it counts as a hang")
    ap.add_argument("--fixtures-only", action="store_true", help="only the repository's fixtures")
    ap.add_argument("-v", "--verbose", action="store_true", help="one line per case")
    args = ap.parse_args()
    t0 = time.perf_counter()
    cases = build_cases(args.seed, args.trunc, args.flip, args.fixtures_only)
    table: dict[str, Counter[str]] = defaultdict(Counter)
    failures = []
    zero_cost = []
    with tempfile.TemporaryDirectory(prefix="damage-sweep-") as tmp:
        for case in cases:
            out = run_case(case, Path(tmp), limit=args.limit)
            table[case.kind][out.result] += 1
            if out.problems:
                failures.append(out)
            if "32MiB" in case.name:
                zero_cost.append((case.name, out.seconds))
            if args.verbose:
                print(f"{out.result:26s} {out.seconds:6.2f} s  {case.name}  {out.codes}  {out.problems}",
                      file=sys.stderr)
    outcomes = ["clean (exit 0)", "damage reported (exit 3)", "refused (exit 1)", "FAIL"]
    print(f"damage sweep: {len(cases)} cases, seed {args.seed}, {time.perf_counter() - t0:.0f} s\n")
    print("| damage kind | cases | " + " | ".join(outcomes) + " |")
    print("|---|---|" + "---|" * len(outcomes))
    for kind in sorted(table):
        row = table[kind]
        print(f"| {kind} | {sum(row.values())} | " + " | ".join(str(row.get(o, 0)) for o in outcomes) + " |")
    total: Counter[str] = sum(table.values(), Counter())
    print(f"| **all** | {sum(total.values())} | " + " | ".join(str(total.get(o, 0)) for o in outcomes) + " |")
    print("\n'clean (exit 0)' cases are damage that changed nothing memlog reads (a flipped byte in an index the "
          "data agrees with, padding) or flipped bytes in formats without checksums (ROS 1, sqlite, MCAP chunks "
          "with CRC 0), which `inspect` says cannot be detected.")
    if zero_cost:
        print("\n| 32 MiB zero-filled tail | seconds (read + inspect + convert) |\n|---|---|")
        for name, sec in zero_cost:
            print(f"| {name} | {sec:.2f} |")
    if failures:
        print(f"\n{len(failures)} failing case(s):")
        for f in failures:
            print(f"- {f.case}: {'; '.join(f.problems)}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
