"""The one exception type for mistakes a user can fix (bad data, bad config, bad paths)."""

from __future__ import annotations

import sys
from collections.abc import Callable


def first_line(err: BaseException) -> str:
    """``TypeName: the first line of its message`` (``TypeName`` when it has none): what a
    one-line error says of an exception it reports."""
    text = str(err).strip()
    return f"{type(err).__name__}: {text.splitlines()[0]}" if text else type(err).__name__


class UserError(Exception):
    """Bad input. The CLI prints ``str(error)`` as one line and exits with code 2.

    The message names the problem and the fix, e.g.
    ``data root /x does not exist: set data.root=... to the folder holding spring/, summer/ ...``

    ``detail`` (a traceback of the user's own code, say) goes to the run log, not the terminal.
    """

    def __init__(self, message: str, detail: str | None = None):
        super().__init__(message)
        self.detail = detail


def exit_code(work: Callable[[], object]) -> int:
    """A command line's ``work()`` as its exit code: 0 when it ends, 2 with the error's one
    line on stderr when it raises ``UserError``."""
    try:
        work()
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0
