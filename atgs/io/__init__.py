"""Input/output shared by every layer: atomic file and directory writes (:mod:`atgs.io.atomic`),
the one video encoder (:mod:`atgs.io.video`), the cache directory (:mod:`atgs.io.cache`) and the
command-line wrapper that keeps the CLIs' promises (:mod:`atgs.io.cli`)."""
