"""The one exception type for mistakes a user can fix (bad data, bad config, bad paths)."""


class UserError(Exception):
    """Bad input. The CLI prints ``str(error)`` as one line and exits with code 2.

    The message names the problem and the fix, e.g.
    ``data root /x does not exist: set data.root=... to the folder holding spring/, summer/ ...``
    """
