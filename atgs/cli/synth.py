"""atgs-synth OUT: render a built-in synthetic multi-view video scene (textured meshes, moving
objects) into the N3DV layout (camXX.mp4 + poses_bounds.npy + synth.json ground truth).
Prepare it with `atgs-prepare OUT --out DIR`, or pass --prepare DIR to do both."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated

import tyro

from atgs.data.synth.videos import EncodeConfig, synthesize
from atgs.data.synth.scene import LAYOUTS, Bounds, Layout, Preset, Rig, Subject, SynthConfig, Walls
from atgs.io.cli import run_cli


@dataclass(frozen=True)
class SynthArgs:
    out: Annotated[Path, tyro.conf.Positional]
    """Output directory for the videos (N3DV layout)."""
    preset: Preset = "large-motion"
    """'small-motion' (N3DV-like) or 'large-motion' (VRU-like: fast, large motion)."""
    frames: int = 120
    """Number of frames per camera."""
    cameras: int = 12
    """Number of cameras (ring: around the scene, alternating two heights; dome: split over its rings)."""
    width: int = 256
    """Frame width in pixels."""
    height: int = 192
    """Frame height in pixels."""
    fps: float = 30.0
    """Frame rate (object speeds are in m/s, so higher fps = smaller motion per frame)."""
    seed: int = 0
    """Seed of textures, colors and motion phases."""
    arc_deg: float = 360.0
    """Spread the cameras over this arc of the ring (360 = all around; e.g. 90 = a converging arc)."""
    rig: Rig = "ring"
    """'ring': cameras on the ring looking at the center; 'front': an N3DV-like front-facing grid
    (two rows, 1.6 m wide, nearly parallel axes); 'dome': a capture stage, --dome-rings rings of
    cameras whose bodies are drawn (the cameras see each other), the backdrop 0.5 m behind them."""
    dome_rings: int = 3
    """Rings of the dome rig: 1 (one height, 1.6 m), 2 (0.8 and 2.6 m) or 3 (0.6, 1.7 and 3.2 m)."""
    subject: Subject = "objects"
    """'objects': the five moving objects; 'person': a 1.75 m figure walking a circle of 1 m radius
    (1 m/s with large-motion, 0.4 m/s with small-motion) and the small orbiting box."""
    people: int = 1
    """--subject person: walkers, 1 or 2 (the second on a 2.4 m circle, the other way round)."""
    walls: Walls = "textured"
    """'grey': a light-grey backdrop and floor, lit evenly, with a faint texture (as a real capture
    stage's, where semi-transparent fog costs the training views almost nothing)."""
    exposure: float = 0.0
    """Give every camera its own exposure: gains spread over +-EXPOSURE stops, black-level offsets
    over +-0.1*EXPOSURE of full scale, applied to its frames (the held-out ground truth too)."""
    texture_contrast: float = 1.0
    """1: the textures as made; towards 0: flatter (0: textureless flat colours)."""
    layout: Layout | None = None
    """A named layout that sets cameras, size and rig (overrides the options it names): 'ring12' (the
    default scene: 12 cameras, 256x192), 'ring10-low' (10 cameras, 200x150), 'front6' (6 cameras,
    front-facing), 'ring12-flat' (the default with textureless surfaces), 'dome24' (a person in a
    3-ring dome of 24 cameras, 320x240), 'dome12-low' (the same with 12 cameras on 2 rings, 200x150),
    'ring10' (10 cameras at one height, 4.6 m out, 200x150), 'sparse4' (4 cameras 90 degrees apart,
    200x150), 'dome-stage' (27 cameras on 3 rings, 320x180: light-grey walls with a faint texture,
    two people, every camera its own exposure: as hard as a real capture stage); the last five are
    dome rigs (visible camera bodies)."""
    bounds: Bounds = "true"
    """Near/far written to poses_bounds.npy (the pixels do not change): 'true' (measured), 'loose'
    (near/10, far*10), 'narrow' (pulled 3/4 of the way to their geometric mean), 'none' (0/0: missing).
    The true ones are in synth.json ("true_near_far")."""
    depth: bool = False
    """Also write the true depth of every frame (depth/<frame>.npz, docs/data.md)."""
    codec: str = "libx264rgb"
    """Video codec: libx264rgb with crf 0 is lossless; libx264 gives ordinary YUV files."""
    crf: int = 0
    """Constant rate factor of libx264 (0 = lossless with libx264rgb)."""
    pix_fmt: str | None = None
    """Pixel format (default: rgb24 for libx264rgb, yuv444p for libx264)."""
    overwrite: bool = False
    """Replace an existing output directory."""
    prepare: Path | None = None
    """Also run atgs-prepare into this directory."""
    keyframes: int = 6
    """Keyframes for --prepare."""


def main(argv: list[str] | None = None) -> int:
    a = tyro.cli(SynthArgs, args=argv, description=__doc__)

    def body() -> None:
        cfg = SynthConfig(frames=a.frames, cameras=a.cameras, width=a.width, height=a.height, seed=a.seed,
                          preset=a.preset, fps=a.fps, arc_deg=a.arc_deg, rig=a.rig,
                          texture_contrast=a.texture_contrast, dome_rings=a.dome_rings, subject=a.subject,
                          bounds=a.bounds, people=a.people, walls=a.walls, exposure=a.exposure)
        if a.layout is not None:
            cfg = replace(cfg, **LAYOUTS[a.layout])
        t = time.perf_counter()
        synthesize(a.out, cfg, EncodeConfig(a.codec, a.crf, a.pix_fmt), overwrite=a.overwrite, depth=a.depth)
        print(f"synthetic scene written to {a.out} in {time.perf_counter() - t:.1f} s")
        if a.prepare is not None:
            from atgs.data.prepare import PrepareConfig, prepare

            t = time.perf_counter()
            prepare(PrepareConfig(src=a.out, out=a.prepare, keyframes=a.keyframes, overwrite=a.overwrite))
            print(f"prepared scene written to {a.prepare} in {time.perf_counter() - t:.1f} s")

    # the scene and encoder settings reject bad values with ValueError (e.g. --cameras 1)
    return run_cli("atgs-synth", body, user_errors=(ValueError,), process=argv is None)


if __name__ == "__main__":
    sys.exit(main())
