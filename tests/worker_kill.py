"""A worker process killed mid-task, from the test side (the package has no test hook for it).

:func:`die_once` also kills a local pool's worker (``tests/test_batch.py``), and :func:`die_now`
is a job whose worker ends at once (``tests/test_workers.py``).

:func:`kill_one_worker` makes every job of :class:`~memlog.steps.ray_pool.RayActors` run through
:func:`die_once`: the first worker to finish a job while the marker file exists removes it and
dies (``os._exit``, no cleanup, as a killed process) before returning the result, so that job
must be run again on the restarted actor. The jobs reach the workers as
``functools.partial(die_once, marker, job_function)``, pickled by reference: the workers import
this module (the Ray tests put this checkout on their ``PYTHONPATH``).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, NoReturn

import pytest


def die_once(marker: str, fn: Callable[..., Any], *job: Any) -> Any:
    """``fn(*job)``, unless this worker is the one that removes ``marker``: then it exits instead of
    returning the result (exactly one worker wins the unlink)."""
    result = fn(*job)
    try:
        os.unlink(marker)
    except FileNotFoundError:
        return result
    os._exit(1)


def die_now(code: int) -> NoReturn:
    """A job whose worker process ends at once, as a process killed for memory does."""
    os._exit(code)


def kill_one_worker(monkeypatch: pytest.MonkeyPatch, marker: Path) -> None:
    """While ``marker`` exists, the first Ray worker to finish a job dies before returning it."""
    from memlog.steps.ray_pool import RayActors

    real = RayActors.map_ordered

    def map_ordered(self: RayActors, fn: Callable[..., Any], jobs: Iterable[tuple[Any, ...]]) -> Iterator[Any]:
        return real(self, functools.partial(die_once, str(marker), fn), jobs)

    monkeypatch.setattr(RayActors, "map_ordered", map_ordered)
