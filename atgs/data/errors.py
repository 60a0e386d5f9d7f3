"""The one exception type of the data layer.

Every problem with user input (missing file, corrupt video, inconsistent poses, ...) raises
:class:`DataError` with a one-line message that names the file or argument and the fix.
The CLIs print it as one line without a traceback and exit with code 2 (``atgs.io.cli``).
"""

from __future__ import annotations

from atgs.errors import UserError


class DataError(UserError):
    """Bad or inconsistent input data; the message is one line meant for the user."""
