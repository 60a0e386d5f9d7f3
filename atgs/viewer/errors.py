"""The one error type of the viewer (a user error: ``atgs-view``/``atgs-render`` print it as one
line and exit with code 2, see atgs.io.cli)."""

from atgs.errors import UserError


class ViewerError(UserError):
    """Bad input or environment; the message is one line and names the fix."""
