"""The README's five-minute tour is what the tests run.

The tour (``memlog map`` the Stromovka autumn drive, ``memlog localize`` the winter drive against it,
``memlog evaluate`` the pair) takes minutes of CPU at camera resolution, and
``tests/test_main_path.py`` already runs exactly those commands through the command line's entry
point on the same shared pair, checking what they write. Rather than run them a second time, this
checks (fast) that the README's tour and that test stay the same commands, that each tour command
parses as a user types it, that its steps feed each other (the map the tour writes is the one it
localizes against), and that the installed ``memlog`` command a user runs starts.
"""

from __future__ import annotations

import ast
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import SHARED, shared

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
MAIN_PATH = ROOT / "tests" / "test_main_path.py"


def tour_lines() -> list[str]:
    """The shell lines of the README's tour section's bash blocks, continued lines joined."""
    text = README.read_text()
    section = text.split("\n## A five-minute tour", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```bash\n(.*?)```", section, re.S)
    return [ln.strip() for b in blocks for ln in b.replace("\\\n", " ").splitlines() if ln.strip()]


def tour_commands() -> list[list[str]]:
    """The tour's ``memlog`` commands as argv (without ``memlog``), ``$D`` as the README sets it."""
    lines = tour_lines()
    setting = next(ln for ln in lines if ln.startswith("D="))
    d = setting.split("&&")[0].strip()[2:]
    return [shlex.split(ln.replace("$D", d))[1:] for ln in lines if ln.startswith("memlog ")]


def _is_path(tok: str) -> bool:
    return "/" in tok or bool(re.search(r"\.(mcap|parquet|json|csv|bag)$", tok))


def normalised(argv: list[str]) -> tuple[str, ...]:
    """``argv`` with ``-q`` left out and every path as ``<path>``."""
    return tuple("<path>" if _is_path(t) else t for t in argv if t not in ("-q", "--quiet"))


def main_path_calls() -> set[tuple[str, ...]]:
    """Every ``main([...])`` call of tests/test_main_path.py, string constants kept, anything
    else (the paths it computes) as ``<path>``."""
    calls = set()
    for node in ast.walk(ast.parse(MAIN_PATH.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "main" and node.args \
                and isinstance(node.args[0], ast.List):
            argv = [e.value if isinstance(e, ast.Constant) and isinstance(e.value, str) else "<path>"
                    for e in node.args[0].elts]
            calls.add(normalised(argv))
    return calls


def test_the_tour_runs_map_localize_evaluate_on_stromovka() -> None:
    cmds = tour_commands()
    assert [c[0] for c in cmds] == ["map", "localize", "evaluate"], cmds
    for c in cmds:
        for tok in c:
            if _is_path(tok) and "stromovka" in tok:
                assert Path(tok).name in {"stromovka_autumn.mcap", "stromovka_winter.mcap", "stromovka_truth.json"}
    if SHARED.exists():  # the files the tour names are the shared data's
        for name in ("stromovka_autumn.mcap", "stromovka_winter.mcap", "stromovka_truth.json"):
            shared(name)


def test_the_tour_is_what_test_main_path_runs() -> None:
    calls = main_path_calls()
    assert calls, "found no main([...]) call in tests/test_main_path.py"
    for c in tour_commands():
        assert normalised(c) in calls, (
            f"the README's tour runs `memlog {shlex.join(c)}`, which tests/test_main_path.py does not run "
            f"(its commands: {sorted(calls)}): keep the two the same")


def _opt(argv: list[str], flag: str) -> str:
    return argv[argv.index(flag) + 1]


def test_the_tour_steps_feed_each_other() -> None:
    map_cmd, loc_cmd, eval_cmd = tour_commands()
    map_out = Path(_opt(map_cmd, "-o"))
    positional = [t for i, t in enumerate(loc_cmd[1:], 1) if not t.startswith("-") and not loc_cmd[i - 1].startswith("-")]
    assert Path(positional[0]) == map_out.with_suffix(".parquet"), "localize must read the Parquet the map step wrote"
    assert Path(_opt(loc_cmd, "--map")) == map_out
    assert Path(_opt(eval_cmd, "--reference")).name == Path(map_cmd[1]).name == "stromovka_autumn.mcap"
    assert Path(_opt(eval_cmd, "--query")).name == Path(positional[1]).name == "stromovka_winter.mcap"
    text = README.read_text()
    for out in (_opt(loc_cmd, "--annotate"), str(map_out), f"{_opt(eval_cmd, '-o')}/report.html",
                _opt(loc_cmd, "-o")):
        assert f"`{out}`" in text or f"'{out}'" in text or f'"{out}"' in text, f"step 4 opens no {out}"


@pytest.mark.parametrize("argv", tour_commands(), ids=lambda a: a[0])
def test_each_tour_command_parses(argv: list[str]) -> None:
    from memlog.cli.app import build_parser

    try:
        build_parser().parse_args(argv)
    except SystemExit as exc:  # argparse: a usage error
        pytest.fail(f"`memlog {shlex.join(argv)}` does not parse (exit {exc.code})")


def test_the_memlog_command_users_run_starts() -> None:
    exe = Path(sys.executable).parent / "memlog"
    if not exe.exists():
        pytest.skip(f"no memlog console script beside {sys.executable} (not installed with pip)")
    run = subprocess.run([str(exe), "--version"], check=False, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.startswith("memlog "), run.stderr
