"""The base of every error meant for the user rather than the developer.

A :class:`UserError` carries a one-line message that names the file or flag at fault and the fix.
Every command line (``atgs.io.cli.run_cli``) prints it as ``<command>: error: <message>`` without a
traceback and exits with code 2. Each layer subclasses it: ``atgs.data.errors.DataError``,
``atgs.checkpoint.CheckpointError``, ``atgs.eval.evaluate.EvalError``,
``atgs.viewer.errors.ViewerError``, ``atgs.headless_gl.HeadlessGLError``,
``atgs.train.trainer.NonFiniteError``, ``atgs.io.gaussian_ply.GaussianPlyError``,
``atgs.export.ExportError``, ``atgs.web.server.ServeError``, ``atgs.device.DeviceError``, ``atgs.config_checks.ConfigError`` and
:class:`OutputError` below.
"""

from __future__ import annotations


class UserError(Exception):
    """Bad input, or a run that cannot go on; the message is one line for the user."""


class OutputError(UserError):
    """An output path that cannot be written, or that exists and may not be replaced."""
