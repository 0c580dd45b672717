"""The one exception type for mistakes a user can fix (bad data, bad config, bad paths)."""


class UserError(Exception):
    """Bad input. The CLI prints ``str(error)`` as one line and exits with code 2.

    The message names the problem and the fix, e.g.
    ``data root /x does not exist: set data.root=... to the folder holding spring/, summer/ ...``

    ``detail`` (a traceback of the user's own code, say) goes to the run log, not the terminal.
    """

    def __init__(self, message: str, detail: str | None = None):
        super().__init__(message)
        self.detail = detail
