"""Volumetric video in a web browser (``atgs-export --format web``, ``atgs-serve``): the chunked
stream of docs/web.md (:mod:`atgs.web.stream_format`), the exporter (:mod:`atgs.web.export`) and
the player page shipped in atgs/web/player/ (JavaScript, copied into every export)."""
