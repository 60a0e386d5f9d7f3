"""Volumetric video in a web browser (``atgs-export --format web``, ``atgs-serve``): the two
streams of docs/web.md (the model itself, :mod:`atgs.web.model_stream`, and the Gaussian chunks,
:mod:`atgs.web.stream_format`), the exporter (:mod:`atgs.web.export`) and the player page
shipped in atgs/web/player/ (JavaScript, copied into every export)."""

# What atgs-export --format web writes unless told (docs/web.md, "Which stream"): the kind chosen
# from bench/results/web.json's bytes-against-PSNR curve, and the model stream's precision.
DEFAULT_STREAM = "model"
DEFAULT_PRECISION = "int8"
