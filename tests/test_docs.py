"""The README and docs/ say what the code does.

* The README is short (at most 260 lines) and starts with the two command blocks: the demo run and
  the test command, which must be ``.ci/run``'s test command, character for character.
* Every relative link in README.md and docs/*.md resolves: the file exists, and an anchor
  (``#...``) is a heading of that file (GitHub's slugs) or an ``<a id>`` in it.
* Every flag of a ``memlog <command>`` quoted in a code block or an inline code span exists in that
  command's parser (:func:`memlog.cli.app.build_parser`; groups do not matter, only the flags).
* The layout section names every package of ``memlog/`` and every module in it.
* docs/benchmarks.md is what ``benchmarks/make_docs.py`` writes from its own sections.

Fast: no model runs, no log is read.
"""

from __future__ import annotations

import argparse
import importlib.util
import re
import subprocess
import sys
import unicodedata
from functools import cache
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]
MAX_README_LINES = 260

_FENCE = re.compile(r"^(```|~~~)")


def code_blocks(text: str) -> list[tuple[str, str]]:
    """``(language, body)`` of every fenced code block."""
    blocks: list[tuple[str, str]] = []
    body: list[str] = []
    lang, inside = "", False
    for line in text.splitlines():
        if _FENCE.match(line.strip()):
            if inside:
                blocks.append((lang, "\n".join(body)))
                inside, body = False, []
            else:
                inside, lang = True, line.strip()[3:].strip()
            continue
        if inside:
            body.append(line)
    return blocks


def prose(text: str) -> str:
    """``text`` without its fenced code blocks (links and inline code are read from this)."""
    out, inside = [], False
    for line in text.splitlines():
        if _FENCE.match(line.strip()):
            inside = not inside
            continue
        if not inside:
            out.append(line)
    return "\n".join(out)


# -- the README's start -------------------------------------------------------------------------

def ci_test_command() -> str:
    """The test command ``.ci/run`` runs (the line after its "keep the two identical" note)."""
    lines = (ROOT / ".ci" / "run").read_text().splitlines()
    cmds = [ln.strip() for ln in lines if "pytest" in ln and ln.strip().startswith("pip install")]
    assert len(cmds) == 1, f".ci/run: expected one test command line, found {cmds}"
    return cmds[0]


def test_readme_is_short() -> None:
    n = len(README.read_text().splitlines())
    assert n <= MAX_README_LINES, f"README.md has {n} lines (at most {MAX_README_LINES}): move detail into docs/"


def test_readme_starts_with_the_two_commands() -> None:
    text = README.read_text()
    head = [ln for ln in text.splitlines() if ln.strip()][:7]
    assert head[0].startswith("# "), head[0]
    assert head[1] == "```bash" and head[3] == "```" and head[4] == "```bash" and head[6] == "```", head
    demo, tests = head[2], head[5]
    assert demo.startswith("pip install . && memlog models prepare && memlog "), demo
    assert "fixtures/demo.mcap" in demo
    assert tests == ci_test_command(), "README's test command and .ci/run's differ:\n" + tests + "\n" + ci_test_command()


# -- links --------------------------------------------------------------------------------------

_LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_ANCHOR_TAG = re.compile(r"<a\s+(?:id|name)=\"([^\"]+)\"", re.I)
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: its rendered text, lower case, without punctuation (letters,
    digits, ``_``, ``-`` and spaces stay), spaces as ``-``."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # links: their text
    text = re.sub(r"<[^>]+>", "", text)  # HTML tags
    text = text.replace("`", "").replace("**", "").replace("*", "")
    text = text.strip().lower()
    kept = []
    for ch in text:
        cat = unicodedata.category(ch)
        if ch in " -_" or cat[0] in "LNM":
            kept.append(ch)
    return "".join(kept).replace(" ", "-")


@cache
def anchors(path: Path) -> frozenset[str]:
    text = path.read_text()
    seen: dict[str, int] = {}
    out = set(_ANCHOR_TAG.findall(text))
    for line in prose(text).splitlines():
        m = _HEADING.match(line)
        if not m:
            continue
        s = slug(m.group(2))
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.add(s if n == 0 else f"{s}-{n}")
    return frozenset(out)


def links(path: Path) -> list[str]:
    text = re.sub(r"`[^`\n]*`", "", prose(path.read_text()))  # not inside inline code
    return _LINK.findall(text)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page: Path) -> None:
    bad = []
    for target in links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # https:, mailto: ...
            continue
        file, _, anchor = target.partition("#")
        dest = (page.parent / file).resolve() if file else page
        if not dest.exists():
            bad.append(f"{target}: {dest} does not exist")
            continue
        if anchor:
            if dest.suffix != ".md":
                bad.append(f"{target}: an anchor into a file that is not Markdown")
            elif anchor not in anchors(dest):
                bad.append(f"{target}: no heading or <a id> {anchor!r} in {dest.name}")
    assert not bad, f"{page.name}:\n" + "\n".join(bad)


def test_the_link_checker_knows_githubs_slugs() -> None:
    assert slug("Shortlists (`--candidates K`)") == "shortlists---candidates-k"
    assert slug("The paper's claim: which reading reproduces it") == "the-papers-claim-which-reading-reproduces-it"
    assert slug("evaluate's outputs (`results.json`, `report.html`)") == "evaluates-outputs-resultsjson-reporthtml"
    assert slug("Drives, not frames: sequence matching") == "drives-not-frames-sequence-matching"
    assert links(ROOT / "docs" / "method.md"), "the link finder finds nothing"


# -- flags --------------------------------------------------------------------------------------

@cache
def parsers() -> dict[str, argparse.ArgumentParser]:
    from memlog.cli.app import build_parser

    top = build_parser()
    sub = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction))
    return {"": top, **dict(sub.choices)}


def flags_of(parser: argparse.ArgumentParser) -> set[str]:
    return {o for a in parser._actions for o in a.option_strings}


_STOP = {"&&", "||", "|", ";", ">", ">>", "2>", "2>&1", "#"}
_START = re.compile(r"(?:^|(?<=[\s`'\"(]))memlog(?=\s)")


def memlog_commands(page: Path) -> list[tuple[str, list[str]]]:
    """``(where, tokens after "memlog")`` of every memlog command quoted in ``page``: in code blocks
    (continued lines joined) and in inline code spans."""
    text = page.read_text()
    snippets = []
    for _lang, body in code_blocks(text):
        snippets += body.replace("\\\n", " ").splitlines()
    snippets += re.findall(r"`([^`\n]+)`", prose(text))
    out = []
    for s in snippets:
        for m in _START.finditer(s):
            rest = s[m.end():]
            tokens = []
            for tok in rest.split():
                if tok in _STOP or tok.startswith("#"):
                    break
                end = tok[-1:] in ("'", '"', ")") and not tok.startswith(("'", '"'))
                tokens.append(tok.rstrip("'\")"))
                if end:
                    break
            # a word after memlog is a command only where memlog starts the command line
            first = s[:m.start()].strip() in ("", "$") or re.search(r"(&&|\|\||;|\$\(|')\s*$", s[:m.start()])
            out.append((s.strip(), tokens if first or (tokens and tokens[0] in parsers()) else []))
    return out


def check_command(tokens: list[str], where: str) -> list[str]:
    """What is wrong with ``memlog TOKENS``: an unknown command or a flag its parser lacks."""
    ps = parsers()
    top = flags_of(ps[""])
    words = [t.strip("[]") for t in tokens]
    i = 0
    while i < len(words) and words[i].startswith("-"):  # memlog -q map ...
        if words[i] not in top:
            return [f"{where}: `memlog {words[i]}` is not a flag of memlog"]
        i += 1
    if i == len(words) or not re.fullmatch(r"[a-z][a-z-]*", words[i]):
        return []  # prose such as "memlog's": no command
    cmd = words[i]
    if cmd not in ps:
        return [f"{where}: `memlog {cmd}` is not a memlog command ({', '.join(sorted(c for c in ps if c))})"]
    known = flags_of(ps[cmd]) | top
    bad = []
    for w in words[i + 1:]:
        w = w.strip("[]()")
        if not w.startswith("-") or w in ("-", "--") or re.fullmatch(r"-[\d.]+", w):
            continue
        flag = w.split("=", 1)[0]
        if not re.fullmatch(r"--?[A-Za-z][\w-]*", flag):
            continue  # "--candidates K|all" gives "K|all": not a flag
        if flag not in known:
            bad.append(f"{where}: `memlog {cmd} {flag}`: no such flag (memlog {cmd} --help)")
    return bad


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_quoted_memlog_flag_exists(page: Path) -> None:
    found = memlog_commands(page)
    bad = [b for where, tokens in found for b in check_command(tokens, where)]
    assert not bad, f"{page.name}:\n" + "\n".join(bad)


def test_the_flag_checker_finds_commands_and_wrong_flags() -> None:
    found = memlog_commands(README)
    cmds = {t[0] for _w, t in found if t}
    assert {"map", "localize", "evaluate", "score", "models"} <= cmds, cmds
    assert check_command(["map", "x.mcap", "--no-such-flag"], "t")
    assert check_command(["mapp", "x.mcap"], "t")
    assert not check_command(["-q", "evaluate", "--reference", "a", "--query", "b", "-o", "c", "--seeds", "2"], "t")
    assert not check_command(["batch", "LOG...", "-o", "OUTDIR", "[--ray", "[ADDRESS]]", "[--workers", "N]"], "t")


# -- layout -------------------------------------------------------------------------------------

def layout_block() -> str:
    text = README.read_text()
    section = text.split("\n## Layout", 1)[1].split("\n## ", 1)[0]
    blocks = code_blocks(section)
    assert blocks, "README's layout section has no code block"
    return blocks[0][1]


def test_layout_names_every_package_and_module() -> None:
    block = layout_block()
    entries: dict[str, str] = {}  # "memlog/io/" -> the text after it, up to the next entry
    parts = re.split(r"(?:(?<=\s)|^)(memlog/(?:[\w]+/)*)(?=\s)", block)
    for i in range(1, len(parts), 2):
        entries[parts[i]] = entries.get(parts[i], "") + " " + parts[i + 1]
    missing = []
    for init in sorted((ROOT / "memlog").rglob("__init__.py")):
        pkg = init.parent
        key = pkg.relative_to(ROOT).as_posix() + "/"
        if key not in entries:
            missing.append(f"package {key}")
            continue
        words = set(re.findall(r"[\w]+", entries[key]))
        for mod in sorted(pkg.glob("*.py")):
            if mod.stem != "__init__" and mod.stem not in words:
                missing.append(f"module {key}{mod.name}")
    assert not missing, "README's layout does not name:\n" + "\n".join(missing)


# -- docs/benchmarks.md -------------------------------------------------------------------------

def make_docs() -> ModuleType:
    spec = importlib.util.spec_from_file_location("make_docs", ROOT / "benchmarks" / "make_docs.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    sys.modules["make_docs"] = mod
    spec.loader.exec_module(mod)
    return mod


def test_benchmarks_page_is_the_generators() -> None:
    md = make_docs()
    page = ROOT / "docs" / "benchmarks.md"
    sections = md.read_sections(page)
    assert set(sections) == set(md.BY_NAME), "docs/benchmarks.md and make_docs.py list other benchmarks"
    assert md.render(sections) == page.read_text(), (
        "docs/benchmarks.md was edited outside its sections: run `python benchmarks/make_docs.py --cached`")
    for name, body in sections.items():  # every section is headed by the command that produced it
        assert re.search(rf'^<a id="{name}"></a>\n## `[^`\n]+`$', body, re.M), name


def test_every_benchmark_script_has_a_section() -> None:
    """A new script in benchmarks/ gets a section (a ``Bench`` in make_docs.py) or is named as not
    being one, so docs/benchmarks.md covers every benchmark."""
    md = make_docs()
    covered = {Path(a).name for b in md.BENCHES for a in b.argv if a.endswith(".py")}
    scripts = {p.name for p in (ROOT / "benchmarks").glob("*.py")}
    missing = scripts - covered - set(md.NOT_SECTIONS)
    assert not missing, f"benchmarks without a section in benchmarks/make_docs.py: {sorted(missing)}"


def test_make_docs_explains_itself() -> None:
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "make_docs.py"), "--help"], check=False,
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    for word in ("--only", "--quick", "--cached", "--list", "docs/benchmarks.md"):
        assert word in run.stdout
    listed = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "make_docs.py"), "--list"], check=False,
                            capture_output=True, text=True, timeout=60)
    assert listed.returncode == 0 and "record_codecs" in listed.stdout, listed.stderr


def test_make_docs_writes_a_section_atomically(tmp_path: Path) -> None:
    """A run replaces its own section and keeps the others (on a copy of the page; no benchmark runs:
    ``run_bench`` is replaced)."""
    md = make_docs()
    page = tmp_path / "benchmarks.md"
    page.write_text((ROOT / "docs" / "benchmarks.md").read_text())
    page.chmod(0o644)
    before = md.read_sections(page)
    def run_bench(b: object, work: Path, scores: Path | None) -> tuple[str, float, tuple[float, float]]:
        return "| a | b |\n|---|---|\n| 1 | 2 |\n", 1.0, (0.5, 0.6)

    md.run_bench = run_bench  # type: ignore[attr-defined]
    assert md.main(["--only", "record_codecs", "--page", str(page), "--work", str(tmp_path / "work")]) == 0
    after = md.read_sections(page)
    assert after["record_codecs"] != before["record_codecs"] and "| 1 | 2 |" in after["record_codecs"]
    assert {k: v for k, v in after.items() if k != "record_codecs"} == \
           {k: v for k, v in before.items() if k != "record_codecs"}
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary file left
    assert page.stat().st_mode & 0o777 == 0o644, "the page's permissions changed"
