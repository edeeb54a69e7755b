"""The layering of ARCHITECTURE.md, checked on the source: every import of a memlog module (at top
level or inside a function, type-checking imports included) goes to the same layer or one below,
and the file-level import graph has no cycle."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent / "memlog"

#: Layers from the bottom; a module may import only from its own layer or lower ones.
LAYERS: list[tuple[str, ...]] = [
    ("memlog._version", "memlog.errors", "memlog.progress", "memlog.configfile", "memlog.settings", "memlog.runtime"),
    ("memlog.io",),
    ("memlog.models",),
    ("memlog.scoring",),
    ("memlog.selection",),
    ("memlog.descriptors",),
    ("memlog.matching",),
    ("memlog.evaluation",),
    ("memlog.outputs",),
    ("memlog.steps",),
    ("memlog.cli", "memlog.__main__", "memlog"),
]


def _modules() -> dict[str, Path]:
    out = {}
    for p in ROOT.rglob("*.py"):
        parts = p.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts).removesuffix(".__init__")
        out[name] = p
    return out


MODULES = _modules()


def layer_of(module: str) -> int:
    """Index of the most specific layer prefix that ``module`` falls under."""
    best, best_len = None, -1
    for i, prefixes in enumerate(LAYERS):
        for pre in prefixes:
            if (module == pre or module.startswith(pre + ".")) and len(pre) > best_len:
                best, best_len = i, len(pre)
    assert best is not None, f"{module} is in no layer of ARCHITECTURE.md"
    return best


def _resolve(name: str) -> str | None:
    while name:
        if name in MODULES:
            return name
        name = name.rpartition(".")[0]
    return None


def imports_of(module: str) -> set[str]:
    """memlog modules that ``module`` imports anywhere in its file."""
    path = MODULES[module]
    is_pkg = path.name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = module.split(".") if is_pkg else module.split(".")[:-1]
                parts = parts[: len(parts) - (node.level - 1)]
                base = ".".join(parts + ([base] if base else []))
            names = [f"{base}.{a.name}" for a in node.names] + [base]
        for n in names:
            if n.split(".")[0] == "memlog":
                t = _resolve(n)
                if t is not None and t != module:
                    found.add(t)
    return found


def test_every_module_has_a_layer() -> None:
    for m in MODULES:
        layer_of(m)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_no_upward_import(module: str) -> None:
    mine = layer_of(module)
    up = sorted(t for t in imports_of(module) if layer_of(t) > mine)
    assert not up, f"{module} (layer {mine}) imports higher layers: {up}"


def test_no_import_cycles() -> None:
    graph = {m: {t for t in imports_of(m) if not (t == m.rpartition('.')[0] or m == t.rpartition('.')[0])}
             for m in MODULES}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    cycles: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def test_the_checks_can_fail() -> None:
    """The layer rule catches an upward import (so the tests above are not vacuous)."""
    assert layer_of("memlog.io.base") < layer_of("memlog.steps.score")
    assert "memlog.io.base" in imports_of("memlog.io.frame") or "memlog.io.image" in imports_of("memlog.io.frame")


def test_the_package_has_no_test_hooks() -> None:
    """Test-only behaviour lives in tests/, not in the package: no module of memlog reads a
    ``MEMLOG_TEST_*`` variable or ends its own process (a test kills a Ray worker from the test
    side: ``tests/worker_kill.py``)."""
    found = [f"{name}: {needle}" for name, path in sorted(MODULES.items())
             for needle in ("MEMLOG_TEST", "os._exit(") if needle in path.read_text(encoding="utf-8")]
    assert not found, f"test hooks in the package: {found}"


def test_library_code_does_not_print() -> None:
    """Library code logs through the ``memlog`` logger; only the command line writes to stdout or
    stderr itself (it decides what is shown)."""
    offenders = []
    for name, path in MODULES.items():
        if name.startswith("memlog.cli") or name == "memlog.__main__":
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "print":
                offenders.append(f"{name}:{node.lineno}")
            if isinstance(node, ast.Attribute) and node.attr in ("stderr", "stdout") and \
                    isinstance(node.value, ast.Name) and node.value.id == "sys" and name != "memlog.progress":
                offenders.append(f"{name}:{node.lineno} sys.{node.attr}")
    assert not offenders, offenders


def test_threads_have_their_own_progress_settings() -> None:
    """Two steps running side by side in threads (``batch --logs-at-once``): one redirecting its
    progress or going quiet does not change what the other does."""
    import threading

    from memlog.progress import is_quiet, progress, redirect, set_quiet

    seen: dict[str, list[str]] = {"a": [], "b": []}
    ready, done = threading.Event(), threading.Event()

    def a() -> None:
        with redirect(lambda desc, unit: seen["a"].append(desc)):
            set_quiet(True)
            ready.set()
            done.wait(5)
            list(progress(range(2), desc="a"))

    def b() -> None:
        ready.wait(5)
        seen["b"].append(f"quiet={is_quiet()}")
        with redirect(lambda desc, unit: seen["b"].append(desc)):
            list(progress(range(3), desc="b"))
        done.set()

    ts = [threading.Thread(target=a), threading.Thread(target=b)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert seen == {"a": ["a", "a"], "b": ["quiet=False", "b", "b", "b"]}


#: Issue 41's limits: a function a reader takes in at once, a module one job.
MAX_FUNCTION_LINES = 100
MAX_MODULE_LINES = 700



def _long_functions(source: str, limit: int) -> list[tuple[str, int, int]]:
    """(name, first line, lines) of every function or method of ``source`` longer than ``limit`` lines
    (decorators not counted)."""
    return [(node.name, node.lineno, node.end_lineno - node.lineno + 1)
            for node in ast.walk(ast.parse(source))
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno is not None
            and node.end_lineno - node.lineno + 1 > limit]


def _environment_reads(source: str) -> list[int]:
    """Lines of ``source`` that read the process environment: ``os.environ`` (any use), ``os.getenv``,
    ``environ`` or ``getenv`` imported from ``os``."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute) and node.attr in ("environ", "getenv", "environb", "getenvb") \
                and isinstance(node.value, ast.Name) and node.value.id == "os":
            lines.append(node.lineno)
        if isinstance(node, ast.ImportFrom) and node.module == "os" and \
                any(a.name in ("environ", "getenv", "environb", "getenvb") for a in node.names):
            lines.append(node.lineno)
    return lines


def test_no_function_over_the_limit() -> None:
    found = [f"{name}.{fn} (line {line}): {n} lines" for name, path in sorted(MODULES.items())
             for fn, line, n in _long_functions(path.read_text(encoding="utf-8"), MAX_FUNCTION_LINES)]
    assert not found, f"functions over {MAX_FUNCTION_LINES} lines: {found}"


def test_no_module_over_the_limit() -> None:
    found = [f"{name}: {n} lines" for name, path in sorted(MODULES.items())
             if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES]
    assert not found, f"modules over {MAX_MODULE_LINES} lines: {found}"


def test_only_the_cli_and_the_api_read_the_environment() -> None:
    found = [f"{name}:{line}" for name, path in sorted(MODULES.items())
             if not (name == "memlog" or name.startswith("memlog.cli"))
             for line in _environment_reads(path.read_text(encoding="utf-8"))]
    assert not found, f"library code reads the environment (pass a memlog.runtime.Runtime instead): {found}"


def test_the_limit_checks_can_fail() -> None:
    """The checks above see what they look for."""
    long_fn = "def f():\n" + "    x = 1\n" * 120
    assert _long_functions(long_fn, MAX_FUNCTION_LINES) == [("f", 1, 121)]
    assert _long_functions("def g():\n    return 1\n", MAX_FUNCTION_LINES) == []
    assert _environment_reads("import os\nv = os.environ.get('X')\n") == [2]
    assert _environment_reads("import os\nv = os.getenv('X')\n") == [2]
    assert _environment_reads("from os import environ\n") == [1]
    assert _environment_reads("import os\nv = os.path.join('a')\n") == []
