"""Analytic description of the built-in synthetic scenes: meshes, textures, motion, cameras.

World frame: z up, ground plane z = 0, the action happens inside a disk of radius ~2.5 around
the origin, enclosed by a cylindrical textured backdrop. Everything is a deterministic function
of :class:`SynthConfig` (the seed drives textures, colors and phases), so the ground truth
geometry of any frame can be rebuilt from the config stored beside the videos.

Objects (their speeds depend on the preset, see ``PRESETS``):
- ``crosser``: a box sliding back and forth across the scene, turning as it goes;
- ``spinner``: a torus spinning about a tilted axis;
- ``jumper``: a sphere that rises out of the ground, hops across and sinks away again
  (enters and leaves the scene);
- ``blob``: a sphere whose surface deforms with travelling waves;
- ``orbiter``: a small box circling the center.

Or (``subject="person"``) a person-sized walker (torso, head, swinging arms and legs) on a circle
of radius 1 m, plus the orbiter; ``people=2`` adds a second walker on a wider circle, the other
way round. The ``dome`` rig is a capture stage: 1-3 rings of cameras whose bodies are drawn, so
that the cameras see each other, inside a backdrop just behind them.

What makes a real stage hard, on request: ``walls="grey"`` gives the backdrop and the floor a
uniform light grey with a faint texture, lit almost evenly (a light wall behind fog makes the
fog cheap for the training views, and stereo finds few points there), and ``exposure`` gives
every camera its own gain and offset (:meth:`SynthScene.exposure_of`), applied to what it
records: its frames and the ground truth rendered for it alike (atgs.data.synth.mesh_renderer).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Literal, get_args

import numpy as np
from PIL import Image

from atgs.cameras import Camera, look_at
from atgs.rotations import axis_angle_matrix

Preset = Literal["small-motion", "large-motion"]
Rig = Literal["ring", "front", "dome"]
Subject = Literal["objects", "person"]
Bounds = Literal["true", "loose", "narrow", "none"]
Walls = Literal["textured", "grey"]
Layout = Literal["ring12", "ring10-low", "front6", "ring12-flat", "dome24", "dome12-low", "ring10", "sparse4",
                 "dome-stage"]
# Named camera layouts of the benchmarks (SynthConfig overrides); "ring12" is the default scene.
LAYOUTS: dict[str, dict] = {
    "ring12": {"cameras": 12, "width": 256, "height": 192, "rig": "ring", "texture_contrast": 1.0},
    "ring10-low": {"cameras": 10, "width": 200, "height": 150, "rig": "ring", "texture_contrast": 1.0},
    "front6": {"cameras": 6, "width": 256, "height": 192, "rig": "front", "texture_contrast": 1.0},
    "ring12-flat": {"cameras": 12, "width": 256, "height": 192, "rig": "ring", "texture_contrast": 0.0},
    # capture stages: a person inside a dome of 3.5 m radius; rings of cameras seeing each other
    "dome24": {"cameras": 24, "width": 320, "height": 240, "rig": "dome", "dome_rings": 3, "ring_radius": 3.5,
               "subject": "person", "texture_contrast": 1.0},
    "dome12-low": {"cameras": 12, "width": 200, "height": 150, "rig": "dome", "dome_rings": 2, "ring_radius": 3.5,
                   "subject": "person", "texture_contrast": 1.0},
    "ring10": {"cameras": 10, "width": 200, "height": 150, "rig": "dome", "dome_rings": 1, "texture_contrast": 1.0},
    "sparse4": {"cameras": 4, "width": 200, "height": 150, "rig": "dome", "dome_rings": 1, "texture_contrast": 1.0},
    # as hard as a real stage: grey walls and floor, 27 cameras (3 rings of 9) of unequal exposure
    # seeing each other, two people walking; 16:9 and small so that it trains on 2 cores
    "dome-stage": {"cameras": 27, "width": 320, "height": 180, "rig": "dome", "dome_rings": 3, "ring_radius": 4.0,
                   "subject": "person", "people": 2, "walls": "grey", "exposure": 0.35, "texture_contrast": 1.0},
}
# rig "dome": (height m, radius as a fraction of ring_radius) of each ring, by the number of rings;
# every camera looks at DOME_TARGET, so the low ring looks slightly up and the high one down
DOME_RINGS: dict[int, tuple[tuple[float, float], ...]] = {
    1: ((1.6, 1.0),),
    2: ((0.8, 1.0), (2.6, 0.8)),
    3: ((0.6, 1.0), (1.7, 1.0), (3.2, 0.75)),
}
DOME_TARGET = np.array([0.0, 0.0, 1.0])
CAMERA_BODY = 0.15  # edge of a camera's box (m); its center sits CAMERA_BEHIND behind the optical center,
CAMERA_BEHIND = 0.1  # so that a camera never sees its own body (the renderer's near plane is 0.05)
# walls="grey": base colours (before shading) and what is left of the texture's contrast; a real
# stage's panels still show seams, screws and dirt, so stereo finds a few points on them
GREY_WALL = np.array([0.93, 0.93, 0.91])
GREY_FLOOR = np.array([0.62, 0.62, 0.6])
GREY_CONTRAST = 0.12
GREY_EVEN_LIGHT = 0.8  # a stage is lit from all around: its walls and floor shade almost evenly
EXPOSURE_OFFSET = 0.1  # exposure: the largest black-level offset per stop of gain spread (of full scale)


@dataclass(frozen=True)
class MotionParams:
    cross_speed: float  # m/s of the crossing box
    cross_span: float  # half length of the crossing path (m)
    spin_rate: float  # revolutions per second of the torus
    hop_period: float  # seconds per hop of the jumper
    deform_amp: float  # relative radius change of the blob
    deform_rate: float  # wave cycles per second
    orbit_rate: float  # revolutions per second of the orbiter
    orbit_radius: float


PRESETS: dict[str, MotionParams] = {
    # N3DV-like: things move, but slowly and locally.
    "small-motion": MotionParams(cross_speed=0.25, cross_span=0.6, spin_rate=0.15, hop_period=2.5,
                                 deform_amp=0.08, deform_rate=0.4, orbit_rate=0.05, orbit_radius=1.6),
    # VRU-like (basketball court): fast, large displacements across the whole scene.
    "large-motion": MotionParams(cross_speed=2.5, cross_span=2.2, spin_rate=1.0, hop_period=0.9,
                                 deform_amp=0.22, deform_rate=1.2, orbit_rate=0.5, orbit_radius=1.8),
}


@dataclass(frozen=True)
class SynthConfig:
    """What to synthesize. Sizes in pixels, time in frames at ``fps``."""

    frames: int = 120
    cameras: int = 12
    width: int = 256
    height: int = 192
    seed: int = 0
    preset: Preset = "large-motion"
    fps: float = 30.0
    ring_radius: float = 4.6  # camera ring radius (m)
    wall_radius: float = 6.5  # backdrop cylinder radius (m)
    fov_x_deg: float = 62.0
    arc_deg: float = 360.0  # cameras spread over this arc of the ring (360: all around; <360: front-facing rig)
    texture_size: int = 512
    # Added after version 2; written by to_dict only when not at their defaults, so the configs
    # (and the cache keys) of existing scenes do not change.
    rig: Rig = "ring"  # "ring": on the ring looking at the center; "front": a planar grid facing +y
    texture_contrast: float = 1.0  # 1 = the textures as made; 0 = flat colors (textureless surfaces)
    dome_rings: int = 3  # rig "dome": rings of cameras (DOME_RINGS)
    subject: Subject = "objects"  # "objects": the five objects below; "person": a walker and the orbiter
    bounds: Bounds = "true"  # near/far written to poses_bounds.npy (atgs.data.synth.videos); never the pixels
    people: int = 1  # subject "person": walkers (1 or 2)
    walls: Walls = "textured"  # "grey": light-grey backdrop and floor with a faint texture (GREY_CONTRAST)
    exposure: float = 0.0  # per-camera gains spread over +-exposure stops, offsets over +-EXPOSURE_OFFSET*exposure

    def to_dict(self) -> dict:
        d = asdict(self)
        for name in _LATE_FIELDS:
            if d[name] == SynthConfig.__dataclass_fields__[name].default:
                del d[name]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SynthConfig":
        return cls(**{k: v for k, v in d.items() if k in cls.__dataclass_fields__})

    @property
    def scene_size(self) -> float:
        """Reference length for error tolerances: the diameter of the camera ring."""
        return 2.0 * self.ring_radius

    @property
    def backdrop_radius(self) -> float:
        """A dome's wall stands 0.5 m behind its outermost cameras, as a capture stage's walls do."""
        return self.ring_radius + 0.5 if self.rig == "dome" else self.wall_radius


_LATE_FIELDS = ("rig", "texture_contrast", "dome_rings", "subject", "bounds", "people", "walls", "exposure")


# --- meshes -----------------------------------------------------------------------------------

@dataclass
class Mesh:
    positions: np.ndarray  # (V,3) float32, object space
    normals: np.ndarray  # (V,3)
    uvs: np.ndarray  # (V,2)
    faces: np.ndarray  # (F,3) int32

    def transformed(self, M: np.ndarray) -> "Mesh":
        p = self.positions @ M[:3, :3].T + M[:3, 3]
        n = self.normals @ np.linalg.inv(M[:3, :3]).T
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
        return Mesh(p.astype(np.float32), n.astype(np.float32), self.uvs, self.faces)


def grid_plane(size: float, n: int, uv_tiles: float) -> Mesh:
    s = np.linspace(-size / 2, size / 2, n + 1)
    x, y = np.meshgrid(s, s, indexing="xy")
    p = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    uv = (p[:, :2] / size + 0.5) * uv_tiles
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    nrm = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    return Mesh(p.astype(np.float32), nrm.astype(np.float32), uv.astype(np.float32), faces.astype(np.int32))


def cylinder_wall(radius: float, height: float, segments: int, uv_tiles: tuple[float, float]) -> Mesh:
    """Open cylinder seen from inside (normals point to the axis)."""
    ang = np.linspace(0, 2 * np.pi, segments + 1)
    rows = 4
    zs = np.linspace(0, height, rows + 1)
    A, Z = np.meshgrid(ang, zs, indexing="xy")
    p = np.stack([radius * np.cos(A).ravel(), radius * np.sin(A).ravel(), Z.ravel()], 1)
    nrm = np.stack([-np.cos(A).ravel(), -np.sin(A).ravel(), np.zeros(A.size)], 1)
    uv = np.stack([A.ravel() / (2 * np.pi) * uv_tiles[0], Z.ravel() / height * uv_tiles[1]], 1)
    idx = np.arange(A.size).reshape(A.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([a, d, c], 1)])
    return Mesh(p.astype(np.float32), nrm.astype(np.float32), uv.astype(np.float32), faces.astype(np.int32))


def box(size: tuple[float, float, float]) -> Mesh:
    h = np.asarray(size, np.float64) / 2
    ps, ns, uvs, fs = [], [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3); n[axis] = sign
            u = np.zeros(3); u[(axis + 1) % 3] = 1.0
            v = np.cross(n, u)
            base = len(ps)
            for cu, cv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                ps.append((n + cu * u + cv * v) * h)
                ns.append(n)
                uvs.append(((cu + 1) / 2 * 0.5 + 0.25 * (axis % 2), (cv + 1) / 2 * 0.5 + 0.25 * (sign > 0)))
            fs += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return Mesh(np.array(ps, np.float32), np.array(ns, np.float32), np.array(uvs, np.float32), np.array(fs, np.int32))


def uv_sphere(radius: float, n_lat: int, n_lon: int) -> Mesh:
    th = np.linspace(0, np.pi, n_lat + 1)
    ph = np.linspace(0, 2 * np.pi, n_lon + 1)
    TH, PH = np.meshgrid(th, ph, indexing="ij")
    n = np.stack([np.sin(TH) * np.cos(PH), np.sin(TH) * np.sin(PH), np.cos(TH)], -1).reshape(-1, 3)
    uv = np.stack([PH.ravel() / (2 * np.pi), TH.ravel() / np.pi], 1)
    idx = np.arange(TH.size).reshape(TH.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, d, c], 1), np.stack([a, c, b], 1)])
    return Mesh((n * radius).astype(np.float32), n.astype(np.float32), uv.astype(np.float32), faces.astype(np.int32))


def torus(R: float, r: float, n_major: int, n_minor: int) -> Mesh:
    u = np.linspace(0, 2 * np.pi, n_major + 1)
    v = np.linspace(0, 2 * np.pi, n_minor + 1)
    U, V = np.meshgrid(u, v, indexing="ij")
    center = np.stack([R * np.cos(U), R * np.sin(U), np.zeros_like(U)], -1)
    nrm = np.stack([np.cos(V) * np.cos(U), np.cos(V) * np.sin(U), np.sin(V)], -1)
    p = center + r * nrm
    uv = np.stack([U.ravel() / (2 * np.pi), V.ravel() / (2 * np.pi)], 1)
    idx = np.arange(U.size).reshape(U.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, d, c], 1), np.stack([a, c, b], 1)])
    return Mesh(p.reshape(-1, 3).astype(np.float32), nrm.reshape(-1, 3).astype(np.float32),
                uv.astype(np.float32), faces.astype(np.int32))


def merge_meshes(meshes: list[Mesh]) -> Mesh:
    """One mesh of many (one draw call, one object in the ground truth)."""
    offsets = np.cumsum([0] + [len(m.positions) for m in meshes[:-1]])
    return Mesh(np.concatenate([m.positions for m in meshes]), np.concatenate([m.normals for m in meshes]),
                np.concatenate([m.uvs for m in meshes]),
                np.concatenate([m.faces + o for m, o in zip(meshes, offsets)]).astype(np.int32))


def vertex_normals(p: np.ndarray, faces: np.ndarray) -> np.ndarray:
    fn = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    n = np.zeros_like(p)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    return n / (np.linalg.norm(n, axis=1, keepdims=True) + 1e-12)


# --- textures ---------------------------------------------------------------------------------

def make_texture(rng: np.random.Generator, size: tuple[int, int], base: np.ndarray, contrast: float = 0.5,
                 shapes_per_mpx: int = 900) -> np.ndarray:
    """(H,W,3) uint8 texture: colored multi-scale noise under many random shapes.

    Nothing repeats (no tiling, no regular grid), so feature matching cannot be fooled by
    look-alike patches, and the shapes give SIFT plenty of corners and blobs.
    """
    from PIL import ImageDraw

    h, w = size
    # smooth noise lives well below full resolution: build it at 1/4 size, upsample once
    hs, ws = max(4, h // 4), max(4, w // 4)
    img = np.zeros((hs, ws, 3), np.float32)
    for cells, wt in ((3, 0.45), (10, 0.3), (32, 0.25), (96, 0.2)):
        small = rng.random((max(2, cells * h // max(h, w)), max(2, cells * w // max(h, w)), 3))
        up = Image.fromarray((small * 255).astype(np.uint8)).resize((ws, hs), Image.BICUBIC)
        img += wt * (np.asarray(up, np.float32) / 255 - 0.5)
    base_img = (np.clip(base[None, None, :] + contrast * img, 0.02, 0.98) * 255).astype(np.uint8)
    out = Image.fromarray(base_img).resize((w, h), Image.BICUBIC)
    draw = ImageDraw.Draw(out)
    n = int(shapes_per_mpx * h * w / 1e6)
    for _ in range(n):
        r = max(h, w) * rng.uniform(0.004, 0.03)
        cx, cy = rng.random() * w, rng.random() * h
        col = tuple(int(v) for v in rng.integers(10, 245, 3))
        kind = rng.integers(0, 3)
        if kind == 0:
            draw.ellipse([cx - r, cy - r * rng.uniform(0.4, 1.0), cx + r, cy + r], fill=col)
        elif kind == 1:
            ang = np.sort(rng.uniform(0, 2 * np.pi, int(rng.integers(3, 6))))
            pts = [(cx + r * np.cos(a), cy + r * np.sin(a)) for a in ang]
            draw.polygon(pts, fill=col)
        else:
            a = rng.uniform(0, np.pi)
            draw.line([cx - r * np.cos(a), cy - r * np.sin(a), cx + r * np.cos(a), cy + r * np.sin(a)],
                      fill=col, width=max(1, int(r * 0.15)))
    fine = np.clip(rng.normal(128, 10, (hs, ws, 3)), 0, 255).astype(np.uint8)
    fine = Image.fromarray(fine).resize((w, h), Image.BILINEAR)
    arr = np.asarray(out, np.int16) + np.asarray(fine, np.int16) - 128
    return np.clip(arr, 0, 255).astype(np.uint8)


def scale_contrast(tex: np.ndarray, contrast: float) -> np.ndarray:
    """The texture pulled towards its mean color (0: one flat color, 1: unchanged)."""
    mean = tex.reshape(-1, 3).mean(0)
    out = mean + float(contrast) * (tex.astype(np.float64) - mean)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def camera_body_texture(size: int = 128) -> np.ndarray:
    """A dark housing with bright lens rings and red tally dots, one in each half of the texture
    (each face of a box shows one half), so that camera bodies stand out in the other views."""
    y, x = (np.mgrid[0:size, 0:size] + 0.5) / size
    r = np.hypot(x % 0.5 - 0.25, y % 0.5 - 0.25)
    img = np.full((size, size, 3), 36, np.uint8)
    img[(r > 0.11) & (r < 0.17)] = (235, 235, 220)
    img[r < 0.04] = (220, 50, 40)
    return img


def grey_textures(rng: np.random.Generator, ts: int) -> list[np.ndarray]:
    """Floor and backdrop of a stage (walls="grey"): the usual textures' pattern, colourless and
    at GREY_CONTRAST of its contrast, around GREY_FLOOR and GREY_WALL."""
    out = []
    for size, base in (((4 * ts, 4 * ts), GREY_FLOOR), ((ts, 8 * ts), GREY_WALL)):
        t = make_texture(rng, size, base, 0.7).astype(np.float64).mean(-1, keepdims=True)
        t = base * 255 + GREY_CONTRAST * (t - t.mean())
        out.append(np.clip(np.round(t), 0, 255).astype(np.uint8))
    return out


def camera_exposures(names: list[str], stops: float, seed: int) -> dict[str, tuple[float, float]]:
    """Per-camera (gain, offset): gains 2**u with u evenly over [-stops, stops], offsets evenly over
    +-EXPOSURE_OFFSET * stops, both in a shuffled order, so that every rig spans the whole range
    whatever the seed. Empty without exposure (every camera records what is rendered)."""
    if stops <= 0 or not names:
        return {}
    rng = np.random.default_rng([seed, 3])
    n = len(names)
    u = rng.permutation(np.linspace(-1.0, 1.0, n)) if n > 1 else np.zeros(1)
    v = rng.permutation(np.linspace(-1.0, 1.0, n)) if n > 1 else np.zeros(1)
    return {name: (float(2.0 ** (stops * a)), float(EXPOSURE_OFFSET * stops * b)) for name, a, b in zip(names, u, v)}


def expose(img: np.ndarray, gain: float, offset: float) -> np.ndarray:
    """What a camera of (gain, offset) records of a rendered uint8 image."""
    if gain == 1.0 and offset == 0.0:
        return img
    out = img.astype(np.float32) * np.float32(gain) + np.float32(255.0 * offset)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


# --- the scene --------------------------------------------------------------------------------

@dataclass
class SceneObject:
    name: str
    mesh: Mesh
    texture: int  # index into SynthScene.textures
    params: dict = field(default_factory=dict)
    static: bool = False


def _M(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    return M


def camera_bodies(cams: list[Camera]) -> Mesh:
    """A box per camera, turned with it, CAMERA_BEHIND behind its center: a point on a body lies
    right behind that camera, as on a real stage."""
    return merge_meshes([box((CAMERA_BODY,) * 3).transformed(_M(c.R.T, c.center - CAMERA_BEHIND * c.forward))
                         for c in cams])


# The walker's parts in its body frame (x forward, y left, z up): box size (or sphere radius),
# texture, pivot, drop of the part's center below the pivot, swing in units of the gait angle.
_PERSON_PARTS = (
    ("torso", (0.24, 0.38, 0.58), 2, (0.0, 0.0, 1.16), 0.0, 0.0),
    ("head", 0.12, 5, (0.0, 0.0, 1.63), 0.0, 0.0),  # top at 1.75 m
    ("leg_l", (0.14, 0.14, 0.84), 3, (0.0, 0.1, 0.87), 0.42, 1.0),
    ("leg_r", (0.14, 0.14, 0.84), 3, (0.0, -0.1, 0.87), 0.42, -1.0),
    ("arm_l", (0.09, 0.09, 0.6), 4, (0.0, 0.25, 1.42), 0.28, -0.7),  # arms swing against the legs
    ("arm_r", (0.09, 0.09, 0.6), 4, (0.0, -0.25, 1.42), 0.28, 0.7),
)
WALK_SPEED = {"small-motion": 0.4, "large-motion": 1.0}  # m/s along the circle
WALK_RADIUS = 1.0  # m, around the z axis
# the second walker: a wider circle, clockwise, slower; clear of the first walker (arms included)
# and of the orbiter's circle (1.6-1.8 m) at every moment
SECOND_WALKER = {"radius": 2.4, "turn": -1.0, "pace": 0.8}
STRIDE = 1.4  # m walked per gait cycle (two steps)
GAIT_SWING = 0.45  # rad, legs' largest angle from the vertical


def person_parts(phase: float, prefix: str = "person", textures: tuple[int, ...] | None = None,
                 walk: dict | None = None) -> list[SceneObject]:
    """The walker's parts, named ``<prefix>_<part>``; ``textures`` replaces the parts' texture
    indices (in _PERSON_PARTS order) and ``walk`` (SECOND_WALKER's keys) its circle."""
    texs = textures or tuple(p[2] for p in _PERSON_PARTS)
    return [SceneObject(f"{prefix}_{name}", uv_sphere(size, 16, 24) if name == "head" else box(size), t,
                        {"phase": phase, "pivot": list(pivot), "drop": drop, "swing": swing, **(walk or {})})
            for (name, size, _, pivot, drop, swing), t in zip(_PERSON_PARTS, texs)]


class SynthScene:
    """All geometry of one synthetic scene; ``meshes_at(frame)`` gives world-space meshes."""

    def __init__(self, cfg: SynthConfig) -> None:
        if cfg.preset not in PRESETS:
            raise ValueError(f"unknown preset {cfg.preset!r}; choose one of {sorted(PRESETS)}")
        self.cfg = cfg
        self.motion = PRESETS[cfg.preset]
        # bounds only matter to the writer (atgs.data.synth.videos) but are checked here, before rendering
        for name, choices in (("subject", get_args(Subject)), ("bounds", get_args(Bounds)), ("walls", get_args(Walls)),
                              ("people", (1, 2)), ("dome_rings", tuple(DOME_RINGS) if cfg.rig == "dome" else None)):
            if choices is not None and getattr(cfg, name) not in choices:
                raise ValueError(f"{name} must be one of {list(choices)}, got {getattr(cfg, name)!r}")
        if not 0.0 <= cfg.exposure <= 2.0:
            raise ValueError(f"exposure must be within 0 and 2 stops, got {cfg.exposure!r}")
        rng = np.random.default_rng(cfg.seed)
        ts = cfg.texture_size
        self.textures = [
            make_texture(rng, (4 * ts, 4 * ts), np.array([0.55, 0.5, 0.42]), 0.7),  # ground, 1 tile
            make_texture(rng, (ts, 8 * ts), np.array([0.45, 0.52, 0.6]), 0.8),  # backdrop, 1 tile around
        ] + [make_texture(rng, (ts, ts), rng.uniform(0.3, 0.75, 3), 0.8, 300) for _ in range(5)]
        if cfg.texture_contrast != 1.0:  # after all random draws: the rest of the scene is unchanged
            self.textures = [scale_contrast(t, cfg.texture_contrast) for t in self.textures]
        ph = rng.uniform(0, 2 * np.pi, 8)
        # what the options below add draws from generators of its own: the rest of the scene is unchanged
        if cfg.walls == "grey":
            self.textures[:2] = grey_textures(np.random.default_rng([cfg.seed, 1]), ts)
        wall = cfg.backdrop_radius
        self.objects = [
            SceneObject("ground", grid_plane(2 * wall + 0.5, 8, 1.0), 0, static=True),
            SceneObject("backdrop", cylinder_wall(wall, 6.0, 96, (1.0, 1.0)), 1, static=True),
        ]
        if cfg.walls == "grey":
            for o in self.objects:
                o.params["even_light"] = GREY_EVEN_LIGHT
        orbiter = SceneObject("orbiter", box((0.35, 0.35, 0.35)), 6, {"phase": float(ph[4])})
        if cfg.subject == "person":  # the walker wears the textures of the objects it replaces
            self.objects += person_parts(float(ph[5])) + [orbiter]
            if cfg.people == 2:  # in clothes of its own
                rng2 = np.random.default_rng([cfg.seed, 2])
                first = len(self.textures)
                self.textures += [scale_contrast(make_texture(rng2, (ts, ts), rng2.uniform(0.2, 0.7, 3), 0.8, 300),
                                                 cfg.texture_contrast) for _ in range(4)]
                texs = tuple(first + t - 2 for _, _, t, *_ in _PERSON_PARTS)  # the parts' 2..5 -> the new four
                self.objects += person_parts(float(ph[5]) + np.pi, "person2", texs, SECOND_WALKER)
        else:
            self.objects += [
                SceneObject("crosser", box((0.7, 0.5, 0.6)), 2, {"phase": float(ph[0]), "dir": float(ph[1])}),
                SceneObject("spinner", torus(0.5, 0.17, 48, 16), 3,
                            {"center": [1.1, -1.0, 0.75], "axis": [0.3, 0.5, 1.0]}),
                SceneObject("jumper", uv_sphere(0.32, 20, 32), 4, {"phase": float(ph[2])}),
                SceneObject("blob", uv_sphere(0.45, 24, 40), 5, {"center": [-1.1, 0.9, 0.62], "phase": float(ph[3])}),
                orbiter,
            ]
        if cfg.rig == "dome":  # camera bodies keep their look whatever texture_contrast is
            self.textures.append(camera_body_texture())
            self.objects.append(SceneObject("camera_bodies", camera_bodies(self.cameras()), len(self.textures) - 1,
                                            static=True))
        self.exposure = camera_exposures([c.name for c in self.cameras()], cfg.exposure, cfg.seed)
        self.light_dir = np.array([0.4, -0.3, 0.85]) / np.linalg.norm([0.4, -0.3, 0.85])

    # --- motion ---------------------------------------------------------------------------
    def time_of(self, frame: int) -> float:
        return frame / self.cfg.fps

    def model_matrix(self, obj: SceneObject, frame: int) -> np.ndarray:
        s, m, p = self.time_of(frame), self.motion, obj.params
        if obj.static or obj.name == "blob":
            c = p.get("center", [0, 0, 0])
            return _M(np.eye(3), np.asarray(c, np.float64))
        if obj.name == "crosser":
            # triangle wave along a line through the center: back and forth across the scene
            period = 4 * m.cross_span / m.cross_speed
            u = (s / period + p["phase"] / (2 * np.pi)) % 1.0
            x = m.cross_span * (abs(4 * u - 2) - 1)  # triangle wave in [-span, span]
            d = np.array([np.cos(p["dir"]), np.sin(p["dir"]), 0.0])
            side = np.array([-d[1], d[0], 0.0])
            pos = x * d + 0.3 * side + np.array([0, 0, 0.3])
            return _M(axis_angle_matrix([0, 0, 1], p["dir"] + 0.8 * x), pos)
        if obj.name == "spinner":
            R = axis_angle_matrix(p["axis"], 2 * np.pi * m.spin_rate * s) @ axis_angle_matrix([1, 0, 0], 0.6)
            return _M(R, np.asarray(p["center"], np.float64))
        if obj.name == "jumper":
            # hops along a line; sunk below the ground for part of each long cycle (enters/leaves)
            cycle = 4 * m.hop_period
            q = (s / cycle + p["phase"] / (2 * np.pi)) % 1.0
            x = -1.8 + 3.6 * q
            hop = abs(np.sin(np.pi * s / m.hop_period))
            ramp = np.clip(min(q, 1 - q) / 0.15, 0, 1)  # 0 at the ends of the path: under ground
            z = -0.4 + ramp * (0.72 + 0.9 * hop)
            return _M(axis_angle_matrix([0, 1, 0], 3 * np.pi * q), np.array([x, 1.6 * np.sin(np.pi * q) - 1.2, z]))
        if obj.name == "orbiter":
            a = 2 * np.pi * m.orbit_rate * s + p["phase"]
            pos = np.array([m.orbit_radius * np.cos(a), m.orbit_radius * np.sin(a), 1.2 + 0.2 * np.sin(3 * a)])
            return _M(axis_angle_matrix([0.2, 1, 0.3], 2 * a), pos)
        if obj.name.startswith(("person_", "person2_")):
            v = WALK_SPEED[self.cfg.preset] * p.get("pace", 1.0)
            radius, turn = p.get("radius", WALK_RADIUS), p.get("turn", 1.0)
            a = p["phase"] + turn * v * s / radius  # turn 1: counter-clockwise, the body's x (forward) at a + 90 deg
            body = _M(axis_angle_matrix([0, 0, 1], a + turn * np.pi / 2),
                      radius * np.array([np.cos(a), np.sin(a), 0.0]))
            R = axis_angle_matrix([0, 1, 0], p["swing"] * GAIT_SWING * np.sin(2 * np.pi * v * s / STRIDE + p["phase"]))
            return body @ _M(R, np.asarray(p["pivot"], np.float64) - R[:, 2] * p["drop"])
        raise KeyError(obj.name)

    def object_space_mesh(self, obj: SceneObject, frame: int) -> Mesh:
        if obj.name != "blob":
            return obj.mesh
        m, s, ph = self.motion, self.time_of(frame), obj.params["phase"]
        n = obj.mesh.normals.astype(np.float64)
        th = np.arccos(np.clip(n[:, 2], -1, 1))
        az = np.arctan2(n[:, 1], n[:, 0])
        w = 2 * np.pi * m.deform_rate * s + ph
        r = 0.45 * (1 + m.deform_amp * np.sin(3 * az + w) * np.sin(2 * th) + 0.5 * m.deform_amp * np.sin(4 * th - 1.3 * w))
        p = n * r[:, None]
        return Mesh(p.astype(np.float32), vertex_normals(p, obj.mesh.faces).astype(np.float32), obj.mesh.uvs, obj.mesh.faces)

    def meshes_at(self, frame: int) -> list[tuple[SceneObject, Mesh]]:
        """World-space meshes of all objects at ``frame``."""
        return [(o, self.object_space_mesh(o, frame).transformed(self.model_matrix(o, frame))) for o in self.objects]

    # --- cameras --------------------------------------------------------------------------
    def exposure_of(self, name: str) -> tuple[float, float]:
        """(gain, offset) of camera ``name``: it records clip(gain * rendered + offset), in [0, 1]
        units; (1, 0) for a camera of no rig (a novel view) or without ``exposure``."""
        return self.exposure.get(name, (1.0, 0.0))

    def cameras(self) -> list[Camera]:
        cfg = self.cfg
        f = 0.5 * cfg.width / np.tan(np.radians(cfg.fov_x_deg) / 2)
        K = np.array([[f, 0, cfg.width / 2], [0, f, cfg.height / 2], [0, 0, 1]])
        if cfg.rig == "front":
            return self._front_cameras(K)
        if cfg.rig == "dome":
            return self._dome_cameras(K)
        cams = []
        for i in range(cfg.cameras):
            if cfg.arc_deg >= 360.0:
                a = 2 * np.pi * i / cfg.cameras
            else:  # evenly over the arc, centered on the -y side
                a = -np.pi / 2 + np.radians(cfg.arc_deg) * (i / max(1, cfg.cameras - 1) - 0.5)
            height = 1.5 if i % 2 == 0 else 2.3  # two rings: a low dome
            eye = np.array([cfg.ring_radius * np.cos(a), cfg.ring_radius * np.sin(a), height])
            cams.append(Camera(f"cam{i:02d}", cfg.width, cfg.height, K, look_at(eye, np.array([0.0, 0.0, 0.6]))))
        return cams

    def _front_cameras(self, K: np.ndarray) -> list[Camera]:
        """N3DV-like front-facing rig: a planar grid of cameras (two rows) on the -y side, 1.6 m
        wide, every camera looking nearly straight ahead (+y) at a point 0.35x its own lateral
        offset, so the optical axes converge only slightly."""
        cfg = self.cfg
        n = cfg.cameras
        cols = (n + 1) // 2
        cams = []
        for i in range(n):
            row, col = divmod(i, cols)
            x = 1.6 * (col / max(1, cols - 1) - 0.5) if cols > 1 else 0.0
            eye = np.array([x, -cfg.ring_radius, 1.3 + 0.6 * row])
            target = np.array([0.35 * x, 0.0, 0.8])
            cams.append(Camera(f"cam{i:02d}", cfg.width, cfg.height, K, look_at(eye, target)))
        return cams

    def _dome_cameras(self, K: np.ndarray) -> list[Camera]:
        """Capture stage: the cameras split over the rings of DOME_RINGS (the lower rings get the
        remainder), evenly around each ring, azimuths staggered between rings."""
        cfg = self.cfg
        rings = DOME_RINGS[cfg.dome_rings]
        cams = []
        for k, (height, radius) in enumerate(rings):
            n = cfg.cameras // len(rings) + (k < cfg.cameras % len(rings))
            for j in range(n):
                a = 2 * np.pi * (j + k / len(rings)) / n
                eye = np.array([radius * cfg.ring_radius * np.cos(a), radius * cfg.ring_radius * np.sin(a), height])
                cams.append(Camera(f"cam{len(cams):02d}", cfg.width, cfg.height, K, look_at(eye, DOME_TARGET)))
        return cams

    def describe(self) -> dict:
        """JSON-able description of the ground truth (the config rebuilds it exactly)."""
        return {
            "config": self.cfg.to_dict(),
            "motion": asdict(self.motion),
            "objects": [{"name": o.name, "static": o.static, "params": o.params,
                         "num_triangles": int(len(o.mesh.faces))} for o in self.objects],
            "scene_size": self.cfg.scene_size,
            **({"exposure": {k: list(v) for k, v in self.exposure.items()}} if self.exposure else {}),
            "world": "z up, ground z=0, backdrop cylinder of radius wall_radius around the z axis",
        }


# --- ground-truth distances -------------------------------------------------------------------

def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance from points p (N,3) to triangles (a,b,c) (N,3 each), elementwise
    (Voronoi-region method of Ericson, Real-Time Collision Detection 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    denom = np.where(np.abs(va + vb + vc) < 1e-30, 1e-30, va + vb + vc)
    v, w = vb / denom, vc / denom
    closest = a + ab * v[..., None] + ac * w[..., None]  # interior
    eps = 1e-30
    # edges
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    t = d1 / np.where(np.abs(d1 - d3) < eps, eps, d1 - d3)
    closest = np.where(m[..., None], a + ab * t[..., None], closest)
    m2 = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    t = d2 / np.where(np.abs(d2 - d6) < eps, eps, d2 - d6)
    closest = np.where(m2[..., None], a + ac * t[..., None], closest)
    m3 = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    t = (d4 - d3) / np.where(np.abs((d4 - d3) + (d5 - d6)) < eps, eps, (d4 - d3) + (d5 - d6))
    closest = np.where(m3[..., None], b + (c - b) * t[..., None], closest)
    # vertices
    closest = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, closest)
    closest = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, closest)
    closest = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, closest)
    return np.linalg.norm(p - closest, axis=-1)


def distance_to_surfaces(scene: SynthScene, frame: int, points: np.ndarray, chunk: int = 256,
                         moving_only: bool = False) -> np.ndarray:
    """Exact distance from each point (N,3) to the nearest rendered triangle at ``frame`` (of the
    moving objects only, if asked)."""
    tris = []
    for obj, mesh in scene.meshes_at(frame):
        if moving_only and obj.static:
            continue
        tris.append(mesh.positions[mesh.faces].astype(np.float64))
    T = np.concatenate(tris)  # (F,3,3)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.empty(len(pts))
    for i in range(0, len(pts), chunk):
        p = pts[i:i + chunk, None, :]
        d = point_triangle_distance(p, T[None, :, 0], T[None, :, 1], T[None, :, 2])
        out[i:i + chunk] = d.min(1)
    return out


def sample_surface(scene: SynthScene, frame: int, n: int, rng: np.random.Generator | None = None,
                   max_radius: float | None = None, moving_only: bool = False) -> np.ndarray:
    """Area-weighted random points on the surfaces at ``frame`` (optionally within a radius of the
    z axis, or on the moving objects only)."""
    rng = rng or np.random.default_rng(0)
    T = np.concatenate([m.positions[m.faces].astype(np.float64) for o, m in scene.meshes_at(frame)
                        if not (moving_only and o.static)])
    area = 0.5 * np.linalg.norm(np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]), axis=1)
    idx = rng.choice(len(T), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = T[idx]
    pts = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    if max_radius is not None:
        pts = pts[np.linalg.norm(pts[:, :2], axis=1) <= max_radius]
    return pts
