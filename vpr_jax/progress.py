"""Progress for long loops: a rich bar on a terminal, nothing in between off one.

Off a terminal (CI, ``nohup``, a log file) a bar only adds noise, so callers also log one
plain line per finished unit of work themselves.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")


def interactive() -> bool:
    return sys.stderr.isatty()


def track(items: Iterable[T], description: str, total: int | None = None) -> Iterator[T]:
    """Yield ``items``, drawing a transient rich bar when stderr is a terminal."""
    if not interactive():
        yield from items
        return
    from rich.progress import track as rich_track

    yield from rich_track(items, description=description, total=total, transient=True)


class Bar:
    """A rich bar over ``total`` units on a terminal; a no-op elsewhere. Use as a context."""

    def __init__(self, total: int, description: str):
        self._progress = None
        if interactive() and total > 0:
            from rich.progress import Progress

            self._progress = Progress(transient=True)
            self._task = self._progress.add_task(description, total=total)

    def __enter__(self) -> Bar:
        if self._progress is not None:
            self._progress.start()
        return self

    def advance(self, n: int = 1) -> None:
        if self._progress is not None:
            self._progress.advance(self._task, n)

    def __exit__(self, *exc) -> None:
        if self._progress is not None:
            self._progress.stop()
