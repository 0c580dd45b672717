"""Progress for long work: the run log (a line per finished unit of work) and rich bars.

A bar is drawn on a terminal only; off one (CI, ``nohup``, a log file) it would only add
noise, so callers also log one plain line per finished unit of work themselves.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")
Log = Callable[[str], None]  # where a reader or a loop reports: print, or a RunLog


class RunLog:
    """Prints every line and, once :meth:`open` names the run's log file, appends it there
    too (lines printed before that are written first, so the file holds the whole run)."""

    def __init__(self):
        self._lines: list[str] = []
        self._path: Path | None = None

    def open(self, path: Path) -> None:
        self._path = path
        with open(path, "a") as f:
            f.writelines(line + "\n" for line in self._lines)

    def __call__(self, line: str) -> None:
        print(line, flush=True)
        self.record(line)

    def record(self, text: str) -> None:
        """Keep ``text`` in the log file only (a traceback the terminal need not show)."""
        if self._path is None:
            self._lines.append(text)
        else:
            with open(self._path, "a") as f:
                f.write(text + "\n")


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

    def advance(self, n: int = 1, description: str | None = None) -> None:
        """``n`` more units done; ``description``: the bar's new label, if given."""
        if self._progress is not None:
            self._progress.update(self._task, advance=n, description=description)

    def __exit__(self, *exc) -> None:
        if self._progress is not None:
            self._progress.stop()
