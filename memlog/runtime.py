"""The runtime context: memlog's settings for this process, and the caches the process keeps.

A :class:`Runtime` holds what used to hide in module globals and environment variables read by
library code:

* the settings: the decoded-pixel cap (``--max-pixels``), the entropy kernel choice, the bound of
  the model cache, the model cache directory, whether internal errors print a traceback, and the
  Ray address; all picklable values;
* the per-process caches, as objects the context owns: :class:`OpenedLogs` (what opening a log
  learned, :mod:`memlog.io._opened`) and :class:`ModelCache` (models loaded once per process,
  :func:`memlog.steps.parallel.cached`).

One Runtime is in force for the process at a time (:func:`current`). The environment is read
once, by the command line and by the package's import (the API), through
:meth:`Runtime.from_environment`; no other memlog module reads it. A setting is changed by
installing a replaced Runtime (:func:`install`, :func:`use`, :meth:`Runtime.replace`): a
replaced Runtime shares the caches of the one it replaces (they are this process's). Executors
give their workers the driver's Runtime (:mod:`memlog.steps.parallel`, :mod:`memlog.steps.ray_pool`):
its settings travel, its caches do not (a Runtime unpickles with empty ones).
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, TypeVar, cast

from memlog.errors import ConfigError, MemlogError, ScoringError

__all__ = ["Runtime", "OpenedLogs", "ModelCache", "current", "install", "use", "DEFAULT_MAX_PIXELS",
           "ENTROPY_KERNELS", "DEVICES", "DEFAULT_SPOOL_BYTES"]

#: Largest image (width x height) memlog decodes unless told otherwise (``--max-pixels``,
#: ``MEMLOG_MAX_PIXELS``): 100 MP is ten times a 4K frame.
DEFAULT_MAX_PIXELS = 100_000_000
#: The entropy kernel choices (``"auto"``: the compiled kernel when it is built).
ENTROPY_KERNELS: tuple[str, ...] = ("auto", "c", "numpy")
#: Models kept per process by default (least recently used dropped first).
DEFAULT_MODEL_CACHE_SIZE = 8
#: Logs whose structure is kept when no reader uses them.
DEFAULT_OPENED_LOGS = 8
#: Bytes of one log's chunks a process keeps in a job's spool (:mod:`memlog.io.spool`) by default.
DEFAULT_SPOOL_BYTES = 8 << 30
#: Where models may run (``auto``: a CUDA GPU when ONNX Runtime offers one).
DEVICES: tuple[str, ...] = ("auto", "cpu", "cuda")

EntropyKernel = Literal["auto", "c", "numpy"]
T = TypeVar("T")


class _Closes(Protocol):
    def close(self) -> None: ...


C = TypeVar("C", bound=_Closes)


# --------------------------------------------------------------------------- caches


def _drop_unused(lock: threading.RLock, entries: OrderedDict[Hashable, _Closes], users: dict[Hashable, int]) -> None:
    with lock:
        for k in [k for k in entries if k not in users]:
            entries.pop(k).close()


class OpenedLogs:
    """What opening logs learned in this process, keyed by file identity (:mod:`memlog.io._opened`).

    An entry is used by readers between :meth:`learned` and :meth:`release`; at most
    ``max_entries`` entries no reader uses are kept, least recently used dropped (closed) first.
    Unused entries are closed when the cache is dropped, and at exit. Thread-safe."""

    def __init__(self, max_entries: int = DEFAULT_OPENED_LOGS) -> None:
        self.max_entries = max_entries
        self._lock = threading.RLock()
        self._entries: OrderedDict[Hashable, _Closes] = OrderedDict()
        self._users: dict[Hashable, int] = {}
        self._scans: dict[str, int] = {}
        weakref.finalize(self, _drop_unused, self._lock, self._entries, self._users)

    def learned(self, key: Hashable, make: Callable[[], C]) -> tuple[C, bool]:
        """The entry of ``key`` (made by ``make()`` when there is none) and whether it was made now.
        The caller uses it until :meth:`release`."""
        with self._lock:
            got = self._entries.get(key)
            if got is not None:
                self._entries.move_to_end(key)
                self._users[key] = self._users.get(key, 0) + 1
                return cast(C, got), False
        made = make()  # outside the lock: a long scan must not block other logs
        with self._lock:
            got = self._entries.get(key)
            if got is not None:  # another thread made it meanwhile: keep one
                made.close()
                self._users[key] = self._users.get(key, 0) + 1
                return cast(C, got), False
            self._entries[key] = made
            self._users[key] = self._users.get(key, 0) + 1
            self._evict()
            return made, True

    def release(self, key: Hashable) -> None:
        """A reader is done with the entry of ``key``."""
        with self._lock:
            n = self._users.get(key, 0) - 1
            if n > 0:
                self._users[key] = n
            else:
                self._users.pop(key, None)
            self._evict()

    def _evict(self) -> None:
        unused = [k for k in self._entries if k not in self._users]
        while len(self._entries) > self.max_entries and unused:
            self._entries.pop(unused.pop(0)).close()

    def clear(self) -> None:
        """Drop every entry no reader uses (closing its temporary files)."""
        _drop_unused(self._lock, self._entries, self._users)

    def users(self, key: Hashable) -> int:
        """How many readers use the entry of ``key`` now."""
        with self._lock:
            return self._users.get(key, 0)

    def __contains__(self, key: object) -> bool:
        with self._lock:
            return key in self._entries

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)

    def count_scan(self, path: str) -> None:
        """Count one full scan of ``path``'s data."""
        with self._lock:
            self._scans[path] = self._scans.get(path, 0) + 1

    def scans(self) -> dict[str, int]:
        """How many times each log's data was scanned in full (a copy)."""
        with self._lock:
            return dict(self._scans)


class ModelCache:
    """Expensive objects (models) made once per key and process, at most ``max_entries`` of them:
    the least recently used is dropped first. Thread-safe (two threads asking for a new key at
    once may both make it; one is kept)."""

    def __init__(self, max_entries: int = DEFAULT_MODEL_CACHE_SIZE) -> None:
        if isinstance(max_entries, bool) or not isinstance(max_entries, int) or max_entries < 1:
            raise ConfigError(f"the model cache size must be an integer >= 1, got {max_entries!r}")
        self.max_entries = max_entries
        self._lock = threading.Lock()
        self._items: OrderedDict[Hashable, Any] = OrderedDict()

    def get(self, key: Hashable, make: Callable[[], T]) -> T:
        """The object of ``key``: ``make()`` when it is not kept."""
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return cast(T, self._items[key])
        value = make()  # outside the lock: loading one model must not block the others
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return cast(T, self._items[key])
            self._items[key] = value
            self._shrink()
            return value

    def resize(self, max_entries: int) -> None:
        """Keep at most ``max_entries`` objects from now on."""
        with self._lock:
            self.max_entries = max_entries
            self._shrink()

    def _shrink(self) -> None:
        while len(self._items) > self.max_entries:
            self._items.popitem(last=False)

    def clear(self) -> None:
        """Drop every object."""
        with self._lock:
            self._items.clear()

    def __contains__(self, key: object) -> bool:
        with self._lock:
            return key in self._items

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)


# --------------------------------------------------------------------------- the context


@dataclass(frozen=True)
class Runtime:
    """memlog's settings for this process, and the caches it keeps.

    ``max_pixels``: the decoded-pixel cap (``--max-pixels``); ``entropy_kernel``: ``"auto"``,
    ``"c"`` or ``"numpy"`` (:func:`memlog.scoring.entropy.entropy_kernel`); ``model_cache_size``:
    models kept per process; ``cache_dir``: the model cache directory (None: ``~/.cache/memlog``);
    ``debug``: internal errors print their traceback; ``ray_address``: the Ray cluster to join
    when none is named (None: a new local instance); ``device``: where models run when a step
    says ``auto`` (``MEMLOG_DEVICE``: ``auto``, a CUDA GPU when ONNX Runtime has one, ``cpu`` or
    ``cuda``; it also reaches the descriptors of ``localize`` and ``evaluate``, which have no flag). ``opened`` and ``models`` are the caches (and
``indexes``: what reading a log's data taught, such as a video topic's keyframes); a
    Runtime made by :meth:`replace` shares them (and its ``model_cache_size`` bounds the shared model
    cache from then on), one that is unpickled has empty ones."""

    max_pixels: int = DEFAULT_MAX_PIXELS
    entropy_kernel: EntropyKernel = "auto"
    model_cache_size: int = DEFAULT_MODEL_CACHE_SIZE
    cache_dir: str | None = None
    debug: bool = False
    ray_address: str | None = None
    device: str = "auto"
    spool_bytes: int = DEFAULT_SPOOL_BYTES
    opened: OpenedLogs = field(default_factory=OpenedLogs, compare=False, repr=False)
    models: ModelCache = field(default_factory=ModelCache, compare=False, repr=False)
    indexes: ModelCache = field(default_factory=lambda: ModelCache(64), compare=False, repr=False)
    spools: dict[str, int] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        _check_int(self.max_pixels, 1, "max pixels")
        if self.entropy_kernel not in ENTROPY_KERNELS:
            raise ScoringError(f"entropy kernel must be one of {', '.join(ENTROPY_KERNELS)}, "
                               f"got {self.entropy_kernel!r}")
        if self.device not in DEVICES:
            raise ConfigError(f"the device must be one of {', '.join(DEVICES)}, got {self.device!r}")
        _check_int(self.spool_bytes, 0, "the spool size", " (bytes)")
        size = self.model_cache_size
        _check_int(size, 1, "the model cache size")
        if self.models.max_entries != size:  # the bound of the Runtime in force
            self.models.resize(size)

    def settings(self) -> dict[str, Any]:
        """The settings (every field but the caches), as keywords of :class:`Runtime`."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.compare}

    def replace(self, **changes: Any) -> Runtime:
        """A Runtime with ``changes`` to the settings, sharing this one's caches."""
        return dataclasses.replace(self, **changes)

    def with_settings_of(self, other: Runtime) -> Runtime:
        """``other``'s settings with this Runtime's caches."""
        return self.replace(**other.settings())

    def cache_path(self) -> Path:
        """The model cache directory: ``cache_dir`` (``~`` expanded), else ``~/.cache/memlog``."""
        if self.cache_dir:
            return Path(self.cache_dir).expanduser()
        return Path.home() / ".cache" / "memlog"

    def __reduce__(self) -> tuple[Any, ...]:
        # Settings travel to a worker; caches are this process's (made empty there).
        return (_rebuild, (self.settings(),))

    @classmethod
    def from_environment(cls, env: Mapping[str, str], *,
                         on_error: Callable[[MemlogError], None] | None = None) -> Runtime:
        """The Runtime the variables of ``env`` ask for (the caller passes the environment):
        ``MEMLOG_MAX_PIXELS``, ``MEMLOG_ENTROPY_KERNEL`` (c, numpy, auto), ``MEMLOG_DEBUG`` (any
        non-empty value), ``MEMLOG_CACHE_DIR``, else ``XDG_CACHE_HOME``/memlog, and
        ``RAY_ADDRESS``, ``MEMLOG_SPOOL_BYTES``; an unset or empty variable means the default. A bad value raises a
        :class:`~memlog.errors.ConfigError` (:class:`~memlog.errors.ScoringError` for the kernel)
        naming the variable; with ``on_error``, the error is handed to it and the default used."""
        kw: dict[str, Any] = {}
        for parse in _PARSERS:
            try:
                kw.update(parse(env))
            except MemlogError as exc:
                if on_error is None:
                    raise
                on_error(exc)
        return cls(**kw)


def _check_int(value: Any, least: int, what: str, unit: str = "") -> None:
    """A ConfigError unless ``value`` is an integer (not a bool) of at least ``least``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ConfigError(f"{what} must be an integer >= {least}{unit}, got {value!r}")


def _rebuild(settings: dict[str, Any]) -> Runtime:
    """A Runtime with ``settings`` and empty caches (how a Runtime unpickles)."""
    return Runtime(**settings)


def _text(env: Mapping[str, str], name: str) -> str:
    return str(env.get(name) or "").strip()


def _int_var(env: Mapping[str, str], name: str, key: str, least: int, unit: str = "") -> dict[str, Any]:
    """``{key: value}`` of the integer variable ``name`` (at least ``least``; ``{}`` when unset)."""
    raw = _text(env, name)
    if not raw:
        return {}
    try:
        n = int(raw)
    except ValueError:
        n = least - 1
    if n < least:
        raise ConfigError(f"{name} must be an integer >= {least}{unit}, got {raw!r}")
    return {key: n}


def _max_pixels(env: Mapping[str, str]) -> dict[str, Any]:
    return _int_var(env, "MEMLOG_MAX_PIXELS", "max_pixels", 1)


def _entropy_kernel(env: Mapping[str, str]) -> dict[str, Any]:
    forced = _text(env, "MEMLOG_ENTROPY_KERNEL").lower()
    if forced not in ("", *ENTROPY_KERNELS):
        raise ScoringError(f"MEMLOG_ENTROPY_KERNEL must be c, numpy or auto, got {forced!r}")
    return {"entropy_kernel": forced} if forced else {}


def _cache_dir(env: Mapping[str, str]) -> dict[str, Any]:
    own = env.get("MEMLOG_CACHE_DIR")
    if own:
        return {"cache_dir": own}
    xdg = env.get("XDG_CACHE_HOME")
    return {"cache_dir": str(Path(xdg) / "memlog")} if xdg else {}


def _debug(env: Mapping[str, str]) -> dict[str, Any]:
    return {"debug": True} if env.get("MEMLOG_DEBUG") else {}


def _device(env: Mapping[str, str]) -> dict[str, Any]:
    raw = _text(env, "MEMLOG_DEVICE").lower()
    if raw not in ("", *DEVICES):
        raise ConfigError(f"MEMLOG_DEVICE must be auto, cpu or cuda, got {raw!r}")
    return {"device": raw} if raw else {}


def _spool_bytes(env: Mapping[str, str]) -> dict[str, Any]:
    return _int_var(env, "MEMLOG_SPOOL_BYTES", "spool_bytes", 0, " (bytes; 0 turns the spool off)")


def _ray_address(env: Mapping[str, str]) -> dict[str, Any]:
    address = env.get("RAY_ADDRESS")
    return {"ray_address": address} if address else {}


#: What :meth:`Runtime.from_environment` reads, one variable (or two, for the cache) each.
_PARSERS: tuple[Callable[[Mapping[str, str]], dict[str, Any]], ...] = (
    _max_pixels, _entropy_kernel, _cache_dir, _debug, _ray_address, _device, _spool_bytes)


# --------------------------------------------------------------------------- the one in force

_LOCK = threading.Lock()
_installed: list[Runtime] = [Runtime()]  # the Runtime in force (one item; the package's import installs its own)


def current() -> Runtime:
    """The Runtime in force in this process."""
    return _installed[0]


def install(runtime: Runtime) -> Runtime:
    """Put ``runtime`` in force for this process (every thread); returns the one it replaces."""
    if not isinstance(runtime, Runtime):
        raise TypeError(f"install() takes a Runtime, got {type(runtime).__name__}")
    with _LOCK:
        before, _installed[0] = _installed[0], runtime
    return before


@contextlib.contextmanager
def use(runtime: Runtime) -> Iterator[Runtime]:
    """``runtime`` in force for this process during the ``with`` block; the one in force before
    (whatever was installed inside the block, e.g. by ``set_max_pixels``) is put back after it."""
    before = install(runtime)
    try:
        yield runtime
    finally:
        install(before)
