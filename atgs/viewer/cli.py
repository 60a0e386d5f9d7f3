"""`atgs-view` (player window or one headless frame) and `atgs-render` (camera-path video).

Both run through atgs.io.cli.run_cli: bad input (ViewerError, CheckpointError, no OpenGL, ...) is
one line on stderr and exit code 2; Ctrl-C is exit code 130 and leaves no partial output."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from atgs.device import DeviceName
from atgs.headless_gl import GLBackend
from atgs.io.cli import run_cli
from atgs.timeline import frame_at
from atgs.viewer.camera_path import CameraPath
from atgs.viewer.camera_path_file import load_camera_path
from atgs.viewer.device import place_source, resolve_device
from atgs.viewer.errors import ViewerError
from atgs.viewer.gl_decode import DecodeRoute
from atgs.viewer.loading import load_source
from atgs.viewer.scene_utils import cameras_path, orbit_center, orbit_path, parse_size, resized, start_camera
from atgs.viewer.splat_renderer import RenderMode, RenderSettings


@dataclass
class DrawOptions:
    """What both commands draw and how: the source, the GL route, the render mode and its
    settings, and the device that prepares frames (the flags atgs-view and atgs-render share)."""

    checkpoint: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="CKPT")]
    """ckpt.pt written by atgs-train, a 3DGS .ply file (a static scene), a folder of per-frame .ply
    files (a sequence, e.g. written by atgs-export), or 'demo' for the built-in synthetic scene."""
    gl: GLBackend = "auto"
    """Headless OpenGL route: auto tries EGL then OSMesa."""
    mode: RenderMode = "color"
    scale_modifier: float = 1.0
    background: tuple[float, float, float] | None = None
    """R G B in [0, 1]; default: the colour the model was trained over (a checkpoint's
    train_config.background: black, or the mean image colour with --train.background-from-images), black for PLY input."""
    min_alpha: float = 1 / 255
    """Alpha cutoff: 1/255 is the training rasterizer's rule; e.g. 4/255 = 0.0157 culls faint
    Gaussians and fragments for speed (docs/viewer.md gives the PSNR cost)."""
    device: DeviceName = "auto"
    """Where frames are decoded, packed and depth sorted: auto = CUDA when torch sees a GPU."""
    decode: DecodeRoute = "torch"
    """torch: frames decoded by torch on --device, then uploaded; gl: decoded and depth sorted in
    OpenGL 4.3 compute shaders, nothing through host memory (for GPUs; slow on llvmpipe: docs/viewer.md)."""


@dataclass
class ViewConfig(DrawOptions):
    """Play a trained ATGS volumetric video or 3D Gaussian splatting PLY files (window), or render one frame headless."""

    headless: bool = False
    """Render one frame to --out without a window (OSMesa or EGL)."""
    time: float = 0.0
    """Normalized time t in [0, 1] (headless; the window opens at t = 0)."""
    frame: int | None = None
    """Frame index instead of --time (a PLY folder: the i-th file in frame-number order)."""
    camera: int = 0
    """Training camera index to render from / open on (PLY input without manifest.json: a camera that frames the scene)."""
    out: Path = Path("frame.png")
    """Headless output image (.png or .jpg)."""
    size: str | None = None
    """WIDTHxHEIGHT of the output (headless) or the window; default: the camera's size (headless), or the
    largest window of the camera's shape within 80% of the screen, at least 960 px wide where it fits."""
    demo_gaussians: int = 20000
    """Gaussians of the built-in 'demo' scene."""
    fps: float | None = None
    """Playback frame rate of PLY input (default: the folder's manifest.json's, else 30)."""
    preload: bool = False
    """Decode every frame before opening the window (smooth playback when decoding is slower than the video)."""
    preload_mb: int = 2048
    """Memory limit of --preload; longer sequences are refused with a message."""
    path: Path | None = None
    """Camera path file of the player's path panel: loaded at start if it exists; its Save writes
    it (default camera_path.json). Render it with atgs-render CKPT --path FILE.json."""
    cache_mb: int = 1024
    """Decoded frames kept (beyond the next few), filled in the background from the start: a
    sequence that decodes slower than real time plays every frame once they are in. 0 keeps
    only the next 8 frames and decodes nothing ahead."""


@dataclass
class RenderConfig(DrawOptions):
    """Render a video of a trained ATGS model (or 3D Gaussian splatting PLY files) along a camera path."""

    out: Path = Path("video.mp4")
    """Video file (.mp4, .mkv, .mov), or a directory name (no suffix) for lossless PNG frames 00000.png, ..."""
    path: str = "orbit"
    """orbit: one revolution around the scene (a front-facing rig: a sweep over the arc its cameras
    cover and back); cameras: move through the training cameras in order;
    FILE.json: a camera path saved by the player (atgs-view), rendered exactly as its preview."""
    fps: float | None = None
    """Video frame rate (default: the path file's, else the sequence's fps)."""
    frames: int | None = None
    """Number of video frames (default: a path file's duration x fps, else one per sequence frame);
    time is resampled to fit."""
    size: str | None = None
    """WIDTHxHEIGHT (default: a path file's size, else the first training camera's; rounded to even)."""


def render_settings(cfg: DrawOptions) -> RenderSettings:
    if not cfg.scale_modifier > 0:
        raise ViewerError(f"--scale-modifier {cfg.scale_modifier}: must be > 0")
    if not 0.0 < cfg.min_alpha < 0.99:
        raise ViewerError(f"--min-alpha {cfg.min_alpha}: must be in (0, 0.99); 1/255 = 0.0039 is the rasterizer's cutoff")
    background = (0.0, 0.0, 0.0) if cfg.background is None else tuple(cfg.background)
    return RenderSettings(mode=cfg.mode, scale_modifier=cfg.scale_modifier, background=background,
                          min_alpha=cfg.min_alpha)


def use_trained_background(settings: RenderSettings, cfg: DrawOptions, source) -> None:
    """Without --background, draw over what the model was trained over, its colour or its
    background by direction (what atgs-eval renders over too), so what no camera saw looks as it
    did in the evaluation."""
    if cfg.background is None:
        settings.background = tuple(float(c) for c in getattr(source, "background", (0.0, 0.0, 0.0)))
        settings.environment = getattr(source, "environment", None)  # its background by direction, if any


def run_headless(cfg: ViewConfig) -> Path:
    from atgs.viewer.headless import HeadlessRenderer
    from atgs.viewer.output import save_image

    settings = render_settings(cfg)
    size = parse_size(cfg.size)
    device = resolve_device(cfg.device)
    source = place_source(load_source(cfg.checkpoint, cfg.demo_gaussians, cfg.fps), device)
    use_trained_background(settings, cfg, source)
    n = source.num_frames
    if cfg.frame is not None:
        if not 0 <= cfg.frame < n:
            raise ViewerError(f"--frame {cfg.frame}: the sequence has frames 0..{n - 1}")
        frame = cfg.frame
    else:
        if not 0.0 <= cfg.time <= 1.0:
            raise ViewerError(f"--time {cfg.time}: normalized time must be within [0, 1]")
        frame = frame_at(cfg.time, n)
    cam = resized(start_camera(source, cfg.camera), size)
    hr = HeadlessRenderer(source, cfg.gl, device, cfg.decode)
    try:
        img = hr.frame_rgb8(frame, cam, settings)
    finally:
        hr.close()
    save_image(cfg.out, img)
    return cfg.out


def run_window(cfg: ViewConfig) -> None:
    """The player window until it is closed."""
    from atgs.viewer.app import PlayerApp, preload_frames

    settings = render_settings(cfg)
    device = resolve_device(cfg.device)
    source = place_source(load_source(cfg.checkpoint, cfg.demo_gaussians, cfg.fps), device)
    use_trained_background(settings, cfg, source)
    preloaded = preload_frames(source, cfg.preload_mb, device) if cfg.preload else None
    app = PlayerApp(source, camera_index=cfg.camera, size=cfg.size, settings=settings, preloaded=preloaded,
                    cache_mb=cfg.cache_mb, device=device, path_file=cfg.path, decode=cfg.decode)
    try:
        app.run()
    finally:
        app.close()


def main(argv: list[str] | None = None) -> int:
    cfg = tyro.cli(ViewConfig, args=argv, prog="atgs-view")

    def body() -> None:
        if cfg.headless:
            print(f"atgs-view: wrote {run_headless(cfg)}")
        else:
            run_window(cfg)

    return run_cli("atgs-view", body, process=argv is None)


def _camera_path_arg(value: str) -> CameraPath | None:
    """--path: the built-in orbit / cameras paths (None), or a path file saved by the player."""
    if value in ("orbit", "cameras"):
        return None
    if value.lower().endswith(".json"):
        return load_camera_path(value)  # a missing or broken file: one line naming it
    raise ViewerError(f"--path {value!r}: expected orbit, cameras, or a camera path .json file saved by atgs-view")


def render_video(cfg: RenderConfig) -> Path:
    from atgs.viewer.output import open_video_output
    from atgs.progress import progress_bar
    from atgs.viewer.headless import HeadlessRenderer, render_sequence

    settings = render_settings(cfg)
    if cfg.fps is not None and not cfg.fps > 0:
        raise ViewerError(f"--fps {cfg.fps}: must be > 0")
    camera_path = _camera_path_arg(cfg.path)
    device = resolve_device(cfg.device)
    source = place_source(load_source(cfg.checkpoint), device)
    use_trained_background(settings, cfg, source)
    F = source.num_frames
    default_n = F if camera_path is None else camera_path.frame_count(cfg.fps)
    n = cfg.frames if cfg.frames is not None else default_n
    if n < 1:
        raise ViewerError(f"--frames {n}: must be >= 1")
    fps = cfg.fps if cfg.fps is not None else float(camera_path.fps if camera_path else source.fps or 30.0)
    cams = list(source.cameras) or [start_camera(source, 0)]
    size = parse_size(cfg.size)
    if size is None:
        w, h = camera_path.size if camera_path and camera_path.size else (cams[0].width, cams[0].height)
        size = (max(2, w - w % 2), max(2, h - h % 2))
    if camera_path is not None:
        path, times = camera_path.render_plan(size[0], size[1], n)
        frames = [frame_at(t, F) for t in times]
    else:
        path = orbit_path(cams, n, orbit_center(source)) if cfg.path == "orbit" else cameras_path(cams, n)
        path = [resized(c, size) for c in path]
        frames = [frame_at(0.0 if n == 1 else i / (n - 1), F) for i in range(n)]
    with open_video_output(cfg.out, size[0], size[1], fps) as writer:
        hr = HeadlessRenderer(source, cfg.gl, device, cfg.decode)
        try:
            with progress_bar(n, "atgs-render", unit="frame") as bar:
                render_sequence(hr, frames, path, settings, lambda i, img: writer.write(img), progress=bar)
        finally:
            hr.close()
    return cfg.out


def render_main(argv: list[str] | None = None) -> int:
    cfg = tyro.cli(RenderConfig, args=argv, prog="atgs-render")
    return run_cli("atgs-render", lambda: print(f"atgs-render: wrote {render_video(cfg)}"),
                   process=argv is None)


if __name__ == "__main__":
    sys.exit(main())
