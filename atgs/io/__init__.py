"""Input/output shared by every layer: atomic file and directory writes (:mod:`atgs.io.atomic`),
the one video encoder (:mod:`atgs.io.video`), the cache directory (:mod:`atgs.io.cache`), the
command-line wrapper that keeps the CLIs' promises (:mod:`atgs.io.cli`), and the 3D Gaussian
splatting PLY format: one file (:mod:`atgs.io.gaussian_ply`) and a folder of per-frame files with
its manifest (:mod:`atgs.io.ply_sequence`)."""
