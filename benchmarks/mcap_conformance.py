#!/usr/bin/env python3
"""The official MCAP conformance corpus through memlog, per feature combination.

    python benchmarks/mcap_conformance.py [--corpus DIR] [--all-rows]

Runs each of the corpus's 416 valid files (``../shared/data/mcap_conformance``) through memlog's
reader, ``memlog inspect`` and ``memlog convert`` (:mod:`tests.mcap_corpus`: the expected records
from the corpus's JSON, a converted file read back by the mcap library) and prints a Markdown
table: per feature combination of the file names (``ch`` chunked, ``mx`` message indexes, ``chx``
chunk indexes, ``st`` statistics, ``sum`` summary offsets, ``pad`` padded records, ``rch``/``rsh``
channels/schemas repeated in the summary, ``ax``/``mdx`` attachment/metadata indexes), how many
files each check passed; then per feature alone. Rows where every check passed are folded into
one line unless ``--all-rows``. Exit status 1 when a file failed a check.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests import mcap_corpus  # noqa: E402

CHECKS = ["read", "inspect", "convert"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--corpus", type=Path, default=mcap_corpus.CORPUS)
    ap.add_argument("--all-rows", action="store_true", help="print every combination, passed or not")
    args = ap.parse_args()
    files = sorted(args.corpus.glob("*/*.mcap"))
    if not files:
        print(f"no corpus at {args.corpus} (../shared/data/mcap_conformance)", file=sys.stderr)
        return 2
    logging.disable(logging.WARNING)
    combos: dict[str, list[int]] = defaultdict(lambda: [0, 0, 0, 0])  # files, then passes per check
    singles: dict[str, list[int]] = defaultdict(lambda: [0, 0, 0, 0])
    failed: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, path in enumerate(files):
            result = [mcap_corpus.check_read(path), mcap_corpus.check_inspect(path),
                      mcap_corpus.check_convert(path, Path(tmp) / f"{i}.mcap")]
            feats = mcap_corpus.features(path)
            for row in [combos[feats]] + [singles[f] for f in feats.split("-")]:
                row[0] += 1
                for k, wrong in enumerate(result):
                    row[k + 1] += not wrong
            if any(result):
                failed.append(f"{path.name}: " + "; ".join(w for r in result for w in r))
    print(f"{len(files)} files; per check, the files that passed\n")
    print("| features | files | " + " | ".join(CHECKS) + " |")
    print("|---|---|" + "---|" * len(CHECKS))
    folded, n_folded = [0, 0, 0, 0], 0
    for feats, row in sorted(combos.items()):
        if args.all_rows or any(n != row[0] for n in row[1:]):
            print(f"| {feats} | " + " | ".join(map(str, row)) + " |")
        else:
            folded, n_folded = [a + b for a, b in zip(folded, row)], n_folded + 1
    if n_folded:
        print(f"| {n_folded} {'other ' if n_folded < len(combos) else ''}combinations, every check passed | "
              + " | ".join(map(str, folded)) + " |")
    total = [sum(r[k] for r in combos.values()) for k in range(4)]
    print("| **all** | " + " | ".join(map(str, total)) + " |")
    print("\n| feature | files | " + " | ".join(CHECKS) + " |")
    print("|---|---|" + "---|" * len(CHECKS))
    for feat, row in sorted(singles.items()):
        print(f"| {feat} | " + " | ".join(map(str, row)) + " |")
    if failed:
        print(f"\n{len(failed)} file(s) failed:")
        for line in failed[:40]:
            print(f"- {line}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
