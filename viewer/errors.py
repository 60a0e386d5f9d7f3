"""The one error type the viewer's command lines turn into a one-line message and exit code 2."""


class ViewerError(Exception):
    """Bad input or environment; the message is one line and names the fix."""
