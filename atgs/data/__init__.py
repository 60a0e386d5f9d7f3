"""Data layer: camera formats, dataset ingest (atgs-prepare), synthetic scenes (atgs-synth) and
the PreparedScene reader. See docs/data.md."""

from atgs.data.errors import DataError
from atgs.data.scene import PreparedScene, write_prepared_scene

__all__ = ["DataError", "PreparedScene", "write_prepared_scene"]
