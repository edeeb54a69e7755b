#!/usr/bin/env python3
"""Frames per second of memlog's commands at camera resolution, with peak memory and where the time goes.

Logs: the shared Stromovka autumn drive (101 frames, 1024x384 JPEG), a longer drive built from it
(``--frames``, default 1010: each frame repeated with small shifts, 2 px to the side per repeat and
a pixel up or down, re-encoded as JPEG quality 95, 10 Hz, written with memlog's MCAP writer to
``--work``) and ``960x540``, the same built from Stromovka's frames resized to 960x540 (``--frames-960``,
default 303: the pixel count of the 960x540 camera drives the speed targets are stated for). Commands, each run as a subprocess of its own (``memlog ... -q``; peak RSS of that
process tree's largest process, ``RUSAGE_CHILDREN`` of a wrapper started for it):

* ``map``: ``memlog map LOG -o MAP`` with the defaults;
* ``score --fast`` and ``score`` (exact; on the built drives only with ``--exact-long``): the
  annotated MCAP of every frame;
* ``evaluate``: ``memlog evaluate`` of the Stromovka pair (autumn reference, winter query, the
  shared truth file); its frames/s counts both drives' frames.

Besides the wall time, the table gives the CPU time per frame (user + system of the command's
processes): less sensitive to other jobs on the machine than frames/s, and frames/s on two idle
cores is at most 2000 / (CPU ms per frame).

Stage shares come from a sampling profile of one more run of each command in one process: every
10 ms each Python thread's CPU time since the last sample goes to the stage its stack is in (the
first memlog stage found from the innermost frame out: ``detector`` (SSD forward), ``entropy``,
``DINOv2``, ``decode`` (JPEG), ``ResMem``, else ``rest``), and the CPU time of the native thread
pools (OpenCV, ONNX Runtime) to the native stages running then. So the shares are of the
process's CPU time (what two cores are busy with), not of the wall time; worker processes
(``--workers``) are not profiled.

``--pythonpath DIR`` runs the commands from another memlog tree (e.g. an export of an earlier
commit) with this machine's environment, for a before/after table under the same conditions.
Timings depend on what else runs on the machine: the table prints the load average around each
command.

    python benchmarks/speed_table.py                       # both logs, every command, profiles
    python benchmarks/speed_table.py --logs stromovka --no-profile
    python benchmarks/speed_table.py --pythonpath /tmp/before --commands map
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
from collections import Counter
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path and "--sample" not in sys.argv:  # (a sample runs the memlog of PYTHONPATH)
    sys.path.insert(0, str(ROOT))
SHARED = Path(os.environ.get("MEMLOG_SHARED_DATA", ROOT.parent / "shared" / "data"))
AUTUMN, WINTER, TRUTH = "stromovka_autumn.mcap", "stromovka_winter.mcap", "stromovka_truth.json"
TOPIC = "/camera/image_raw/compressed"
COMMANDS = ("map", "score-fast", "score", "evaluate")
EXTRA = ("map-w2",)
STAGES = ("detector", "entropy", "DINOv2", "decode", "ResMem", "rest")

# the first of these found from the innermost Python frame out names a sample's stage: (file part, function)
_STAGE_FRAMES: tuple[tuple[str, str, str], ...] = (
    ("detector", "memlog/models/detector.py", "forward"),
    ("detector", "memlog/scoring/staticity.py", "detect"),
    ("entropy", "memlog/scoring/entropy.py", ""),
    ("entropy", "skimage/filters/rank", ""),
    ("DINOv2", "memlog/descriptors/dinov2.py", ""),
    ("DINOv2", "memlog/models/dinov2.py", ""),
    ("DINOv2", "memlog/descriptors/patches.py", ""),
    ("ResMem", "memlog/scoring/memorability.py", ""),
    ("ResMem", "memlog/models/resmem.py", "run_crops"),
    ("decode", "memlog/io/image.py", ""),
)
# a thread whose innermost frame is one of these is waiting, not working
_IDLE = (("threading.py", "wait"), ("threading.py", "_wait_for_tstate_lock"), ("queue.py", "get"),
         ("concurrent/futures/thread.py", "_worker"), ("concurrent/futures/_base.py", "result"),
         ("selectors.py", "select"), ("multiprocessing/connection.py", "_recv"),
         ("multiprocessing/connection.py", "wait"), ("threading.py", "join"))


# -- the long drive ----------------------------------------------------------------------------------
def long_drive(out: Path, frames: int, size: tuple[int, int] | None = None) -> Path:
    """Stromovka autumn, each frame repeated with small shifts until ``frames`` frames (10 Hz);
    ``size`` (width, height): each frame first resized to it (960x540: the pixel count of the
    960x540 camera drives the speed targets are stated for; Stromovka's 1024x384 stretched)."""
    import cv2
    import numpy as np
    from rosbags.typesys import Stores, get_typestore

    from memlog.io import McapLogWriter, open_log

    path = out / (f"stromovka_long_{frames}.mcap" if size is None else f"stromovka_{size[0]}x{size[1]}_{frames}.mcap")
    if path.exists():
        return path
    store = get_typestore(Stores.ROS2_HUMBLE)
    with open_log(SHARED / AUTUMN) as reader:
        msgs = list(reader.messages([TOPIC]))
        start = reader.info().start_ns
        profile = reader.profile
    assert start is not None and msgs
    ctype = msgs[0].channel.msgtype
    reps = -(-frames // len(msgs))
    with McapLogWriter(path, profile=profile) as w:
        j = 0
        for src in msgs:
            m = store.deserialize_cdr(src.data, ctype)
            img = cv2.imdecode(np.frombuffer(bytes(m.data), np.uint8), cv2.IMREAD_COLOR)
            if size is not None:
                img = cv2.resize(img, size, interpolation=cv2.INTER_LINEAR)
            for r in range(reps):
                if j >= frames:
                    break
                shift = np.float32([[1, 0, 2 * r], [0, 1, (r % 3) - 1]])
                moved = cv2.warpAffine(img, shift, (img.shape[1], img.shape[0]), borderMode=cv2.BORDER_REFLECT)
                data = np.frombuffer(cv2.imencode(".jpg", moved, [cv2.IMWRITE_JPEG_QUALITY, 95])[1], np.uint8)
                stamp = int(start + j * 100_000_000)
                sec, nsec = divmod(stamp, 1_000_000_000)
                header = store.types["std_msgs/msg/Header"](
                    stamp=store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=m.header.frame_id)
                msg = store.types[ctype](header=header, format=m.format, data=data)
                w.write(w.channel_for(src.channel), stamp, bytes(store.serialize_cdr(msg, ctype)), sequence=j)
                j += 1
    return path


def frame_count(log: Path) -> int:
    from memlog.io import FrameWindow, open_log

    with open_log(log) as reader:
        return int(reader.count_frames(FrameWindow()))


# -- running and measuring ---------------------------------------------------------------------------
_WRAPPER = """
import json, resource, subprocess, sys, time
t = time.perf_counter()
rc = subprocess.run(sys.argv[1:]).returncode
u = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({"rc": rc, "seconds": time.perf_counter() - t, "cpu_seconds": u.ru_utime + u.ru_stime,
                  "peak_rss_mb": u.ru_maxrss / 1024.0}))
"""


def _env(pythonpath: str | None) -> dict[str, str]:
    env = dict(os.environ)
    pythonpath = pythonpath or str(ROOT)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def command(name: str, log: Path, out: Path) -> list[str]:
    """The memlog command line of ``name`` on ``log`` (outputs under ``out``)."""
    if name == "map":
        return ["map", str(log), "-o", str(out / "map.mcap"), "-q"]
    if name == "map-w2":
        return ["map", str(log), "-o", str(out / "map.mcap"), "--workers", "2", "-q"]
    if name == "score-fast":
        return ["score", str(log), "-o", str(out / "fast.mcap"), "--fast", "-q"]
    if name == "score":
        return ["score", str(log), "-o", str(out / "exact.mcap"), "-q"]
    if name == "evaluate":
        return ["evaluate", "--reference", str(SHARED / AUTUMN), "--query", str(SHARED / WINTER), "--truth",
                str(SHARED / TRUTH), "-o", str(out / "evaluate"), "-q"]
    raise ValueError(name)


def run(args: list[str], pythonpath: str | None, cwd: Path) -> dict[str, Any]:
    """One ``memlog`` command as a subprocess (in ``cwd``): exit code, seconds, peak RSS, load
    average around it."""
    load0 = os.getloadavg()[0]
    cmd = [sys.executable, "-c", _WRAPPER, sys.executable, "-m", "memlog", *args]
    # (not from the repository: `python -m` puts the working directory first on the path)
    p = subprocess.run(cmd, env=_env(pythonpath), capture_output=True, text=True, cwd=cwd)
    if p.returncode != 0 or not p.stdout.strip():
        raise RuntimeError(f"memlog {' '.join(args)} failed:\n{p.stderr[-3000:]}")
    res: dict[str, Any] = json.loads(p.stdout.strip().splitlines()[-1])
    if res["rc"] != 0:
        raise RuntimeError(f"memlog {' '.join(args)} exited {res['rc']}:\n{p.stderr[-3000:]}")
    res["load"] = (round(load0, 1), round(os.getloadavg()[0], 1))
    return res


def profile(args: list[str], pythonpath: str | None, out: Path) -> dict[str, float]:
    """Stage shares of one more run of ``memlog ARGS`` in one process (this script's ``--sample``)."""
    dest = out / "stages.json"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--sample", str(dest), "--", *args]
    p = subprocess.run(cmd, env=_env(pythonpath), capture_output=True, text=True, cwd=out)
    if p.returncode != 0:
        raise RuntimeError(f"profiling memlog {' '.join(args)} failed:\n{p.stderr[-3000:]}")
    got = json.loads(dest.read_text())
    counts: dict[str, float] = got["counts"]
    if pythonpath and not str(got["memlog"]).startswith(str(Path(pythonpath).resolve())):
        raise RuntimeError(f"the profile ran {got['memlog']}, not the memlog of {pythonpath}")
    total = sum(counts.values()) or 1
    return {s: counts.get(s, 0) / total for s in STAGES}


def _stage_of(frame: Any) -> str | None:
    """The stage of one thread's stack (None: waiting)."""
    f = frame
    innermost = True
    while f is not None:
        code = f.f_code
        fn = code.co_filename.replace(os.sep, "/")
        if innermost and any(fn.endswith(a) and code.co_name == b for a, b in _IDLE):
            return None
        innermost = False
        for stage, part, func in _STAGE_FRAMES:
            if part in fn and (not func or code.co_name == func):
                return stage
        f = f.f_back
    return "rest"


_NATIVE = ("detector", "DINOv2", "ResMem", "decode")  # stages that run in native thread pools too


def _cpu_ticks(path: str) -> int:
    """utime + stime of a /proc stat file (clock ticks)."""
    with open(path, "rb") as fh:
        fields = fh.read().rsplit(b")", 1)[1].split()
    return int(fields[11]) + int(fields[12])


def sample(dest: Path, argv: list[str], every_s: float = 0.01) -> int:
    """Run ``memlog ARGV`` here while sampling every thread; write CPU time per stage to ``dest``.

    Each sample reads each Python thread's CPU time (``/proc/self/task/TID/stat``) and gives what
    it used since the last sample to the stage its stack is in; CPU used by threads without Python
    frames (OpenCV's and ONNX Runtime's pools) goes to the native stages running at that moment
    (detector, DINOv2, ResMem, decode; split evenly), else to ``rest``."""
    from memlog.cli import main

    counts: Counter[str] = Counter()
    stop = threading.Event()
    own: list[int] = []

    def sampler() -> None:
        own.append(threading.get_ident())
        last: dict[int, int] = {}
        last_total = _cpu_ticks("/proc/self/stat")
        while not stop.wait(every_s):
            threads = {t.ident: t.native_id for t in threading.enumerate() if t.ident not in own}
            total = _cpu_ticks("/proc/self/stat")
            used_py = 0
            native_now: list[str] = []
            for tid, frame in sys._current_frames().items():
                nid = threads.get(tid)
                if nid is None:
                    continue
                try:
                    ticks = _cpu_ticks(f"/proc/self/task/{nid}/stat")
                except OSError:
                    continue
                d = ticks - last.get(nid, ticks)
                last[nid] = ticks
                st = _stage_of(frame) or "rest"
                counts[st] += d
                used_py += d
                if st in _NATIVE:
                    native_now.append(st)
            rest = total - last_total - used_py
            last_total = total
            if rest > 0:
                for st in native_now or ["rest"]:
                    counts[st] += rest / max(1, len(native_now))

    t = threading.Thread(target=sampler, daemon=True)
    t.start()
    try:
        rc = main(argv)
    finally:
        stop.set()
        t.join()
    import memlog

    dest.write_text(json.dumps({"counts": dict(counts), "memlog": memlog.__file__}))
    return rc


# -- the table ------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="/tmp/memlog_speed", help="where the long drive and the outputs go")
    ap.add_argument("--frames", type=int, default=1010, help="frames of the long drive")
    ap.add_argument("--logs", default="960x540,stromovka,long", help="960x540, stromovka and/or long")
    ap.add_argument("--frames-960", type=int, default=303, help="frames of the 960x540 drive")
    ap.add_argument("--commands", default=",".join(COMMANDS),
                    help=f"of {', '.join(COMMANDS)}, map-w2 (`memlog map --workers 2`)")
    ap.add_argument("--exact-long", action="store_true", help="also `memlog score` (exact) on the long drive")
    ap.add_argument("--no-profile", action="store_true", help="no stage shares (no second run)")
    ap.add_argument("--profile-logs", default="960x540,stromovka,long", help="the logs whose commands are profiled")
    ap.add_argument("--pythonpath", help="run memlog from this tree (before/after comparisons)")
    ap.add_argument("--json", help="also write the rows as JSON here")
    ap.add_argument("--sample", help=argparse.SUPPRESS)
    ap.add_argument("rest", nargs="*", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.sample:
        return sample(Path(a.sample), a.rest)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    logs: dict[str, Path] = {}
    for name in a.logs.split(","):
        if name == "stromovka":
            logs[name] = SHARED / AUTUMN
        elif name == "long":
            logs[name] = long_drive(work, a.frames)
        elif name == "960x540":
            logs[name] = long_drive(work, a.frames_960, (960, 540))
        else:
            ap.error(f"unknown log {name!r}")
    rows: list[dict[str, Any]] = []
    for lname, log in logs.items():
        n = frame_count(log)
        for cname in a.commands.split(","):
            if cname not in COMMANDS + EXTRA:
                ap.error(f"unknown command {cname!r}")
            if cname == "evaluate" and lname != "stromovka":
                continue  # the pair: Stromovka autumn/winter
            if cname == "score" and lname != "stromovka" and not a.exact_long:
                continue
            out = work / f"{lname}-{cname}"
            shutil.rmtree(out, ignore_errors=True)
            out.mkdir(parents=True)
            args = command(cname, log, out)
            frames = n + (frame_count(SHARED / WINTER) if cname == "evaluate" else 0)
            res = run(args, a.pythonpath, out)
            row: dict[str, Any] = {"log": lname, "frames": frames, "command": cname, **res,
                                   "fps": frames / res["seconds"]}
            if not a.no_profile and lname in a.profile_logs.split(","):
                shutil.rmtree(out, ignore_errors=True)
                out.mkdir(parents=True)
                row["stages"] = profile(args, a.pythonpath, out)
            rows.append(row)
            print(f"# {lname} {cname}: {row['fps']:.2f} frames/s, {res['seconds']:.1f} s, "
                  f"peak RSS {res['peak_rss_mb']:.0f} MB, load {res['load']}", file=sys.stderr, flush=True)
    import memlog

    where = a.pythonpath or str(Path(memlog.__file__).resolve().parent.parent)
    print(f"memlog from {where}; {os.cpu_count()} cores; Python {sys.version.split()[0]}\n")
    print("| log | frames | command | seconds | frames/s | CPU ms/frame | peak RSS (MB) | load avg before/after |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['log']} | {r['frames']} | {r['command']} | {r['seconds']:.1f} | {r['fps']:.2f} | "
              f"{1e3 * r['cpu_seconds'] / r['frames']:.0f} | {r['peak_rss_mb']:.0f} | {r['load'][0]} / {r['load'][1]} |")
    if any("stages" in r for r in rows):
        print("\nShare of CPU time per stage (sampling profile of a separate run):\n")
        print("| log | command | " + " | ".join(STAGES) + " |")
        print("|---|---|" + "---|" * len(STAGES))
        for r in rows:
            if "stages" in r:
                print(f"| {r['log']} | {r['command']} | " + " | ".join(f"{100 * r['stages'][s]:.0f} %" for s in STAGES)
                      + " |")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
