"""The camera path file (JSON, versioned): written by the player, read by the player and atgs-render.

Format (version 1; docs/viewer.md has the full description)::

    {
      "format": "atgs-camera-path",
      "version": 1,
      "duration_s": 6.0,            # video length in seconds (> 0)
      "fps": 30.0,                  # video frame rate (> 0); frames = round(duration_s * fps)
      "size": [960, 720],           # optional default video size (the player writes its window size)
      "keyframes": [                # at least one, in video order (video_t strictly increasing)
        {"video_t": 0.0,            # position in the video, fraction of its duration, in [0, 1]
         "scene_t": 0.25,           # normalized sequence time shown there (frame = round(t (F - 1)))
         "fov_y_deg": 50.0,         # vertical field of view in degrees, in (0, 180)
         "w2c": [[...], [...], [...], [0, 0, 0, 1]]}   # 4x4 world-to-camera, OpenCV axes
      ]
    }

Poses are stored as in ``atgs.cameras.Camera``: a row-major 4x4 world-to-camera matrix in OpenCV
axes (x right, y down, z forward), so the camera center is ``-R^T t``. Intrinsics are not
stored: a path is rendered at any size with square pixels, the principal point at the image
center and the keyframes' vertical field of view. Unknown keys are ignored (room for later
additions within version 1); a newer version is refused with a message.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from atgs.viewer.camera_path import CameraPath, PathKey
from atgs.viewer.errors import ViewerError
from atgs.io.atomic import write_bytes_atomic

FORMAT = "atgs-camera-path"
VERSION = 1
MAX_FRAMES = 1_000_000  # a typo in duration_s or fps must not start a days-long render
ROTATION_TOLERANCE = 1e-3  # hand-edited files with rounded numbers are projected onto a rotation


def path_to_json(path: CameraPath) -> str:
    """The file's text: one keyframe per line block, every float written exactly (repr)."""
    head = {"format": FORMAT, "version": VERSION, "duration_s": float(path.duration_s), "fps": float(path.fps),
            "size": None if path.size is None else [int(path.size[0]), int(path.size[1])]}
    lines = ["{"] + [f"  {json.dumps(k)}: {json.dumps(v)}," for k, v in head.items()] + ['  "keyframes": [']
    for i, k in enumerate(path.keys):
        rows = ",\n             ".join(json.dumps([float(x) for x in row]) for row in k.w2c)
        sep = "," if i < len(path.keys) - 1 else ""
        lines.append(f'    {{"video_t": {json.dumps(k.video_t)}, "scene_t": {json.dumps(k.scene_t)}, '
                     f'"fov_y_deg": {json.dumps(k.fov_y_deg)},\n     "w2c": [{rows}]}}{sep}')
    lines += ["  ]", "}"]
    return "\n".join(lines) + "\n"


def save_camera_path(path: CameraPath, file: str | Path) -> Path:
    """Write atomically (an existing file is replaced only by a complete one)."""
    if not path.keys:
        raise ViewerError(f"{file}: the path has no keyframes; add one (K) before saving")
    file = Path(file)
    write_bytes_atomic(file, path_to_json(path).encode())
    return file


def load_camera_path(file: str | Path) -> CameraPath:
    """Read and check a path file; any problem is a one-line ViewerError naming the file."""
    file = Path(file)
    if not file.is_file():
        raise ViewerError(f"{file}: camera path file not found; save one from the player (atgs-view, camera path panel)")
    try:
        text = file.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ViewerError(f"{file}: cannot read the camera path ({type(exc).__name__}: {exc})") from None
    if not text.strip():
        raise ViewerError(f"{file}: empty file, not a camera path; save one from the player (atgs-view)")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ViewerError(f"{file}: not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno}); "
                          "fix it or save the path again from the player") from None
    return path_from_dict(data, str(file))


def path_from_dict(data: object, where: str) -> CameraPath:
    def fail(msg: str) -> ViewerError:
        return ViewerError(f"{where}: {msg}")

    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise fail(f'not an ATGS camera path (expected a JSON object with "format": "{FORMAT}")')
    version = data.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise fail(f'"version" must be a positive integer, got {version!r}')
    if version > VERSION:
        raise fail(f"camera path version {version} is newer than this atgs reads ({VERSION}); update atgs")
    duration = _number(data.get("duration_s"), "duration_s", fail)
    fps = _number(data.get("fps"), "fps", fail)
    if duration <= 0 or fps <= 0:
        raise fail(f"duration_s and fps must be > 0, got {duration} and {fps}")
    if duration * fps > MAX_FRAMES:
        raise fail(f"duration_s x fps = {duration * fps:.0f} frames is more than {MAX_FRAMES}; check both")
    size = data.get("size")
    if size is not None:
        if (not isinstance(size, list) or len(size) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 16384 for v in size)):
            raise fail(f'"size" must be [width, height] in pixels (1..16384) or null, got {size!r}')
        size = (size[0], size[1])
    raw_keys = data.get("keyframes")
    if not isinstance(raw_keys, list):
        raise fail('"keyframes" must be a list of keyframes')
    if not raw_keys:
        raise fail("the path has no keyframes; add at least one in the player (K)")
    keys = [_key(k, f"keyframes[{i}]", fail) for i, k in enumerate(raw_keys)]
    for i in range(1, len(keys)):
        if keys[i].video_t <= keys[i - 1].video_t:
            raise fail(f"keyframes[{i}].video_t {keys[i].video_t} is not after keyframes[{i - 1}].video_t "
                       f"{keys[i - 1].video_t}; keyframes must be in video order")
    return CameraPath(keys=keys, duration_s=duration, fps=fps, size=size)


def _number(v: object, name: str, fail) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise fail(f'"{name}" must be a finite number, got {v!r}')
    return float(v)


def _key(raw: object, name: str, fail) -> PathKey:
    if not isinstance(raw, dict):
        raise fail(f"{name} must be an object with video_t, scene_t, fov_y_deg and w2c")
    vt = _number(raw.get("video_t"), f"{name}.video_t", fail)
    st = _number(raw.get("scene_t"), f"{name}.scene_t", fail)
    fov = _number(raw.get("fov_y_deg"), f"{name}.fov_y_deg", fail)
    if not (0.0 <= vt <= 1.0 and 0.0 <= st <= 1.0):
        raise fail(f"{name}: video_t and scene_t must be within [0, 1], got {vt} and {st}")
    if not 0.0 < fov < 180.0:
        raise fail(f"{name}.fov_y_deg {fov}: must be within (0, 180) degrees")
    try:
        w2c = np.array(raw.get("w2c"), dtype=np.float64)
    except (TypeError, ValueError):
        w2c = np.zeros(0)
    if w2c.shape != (4, 4) or not np.all(np.isfinite(w2c)):
        raise fail(f"{name}.w2c must be a 4x4 matrix of finite numbers (OpenCV world-to-camera)")
    if np.abs(w2c[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-9:
        raise fail(f"{name}.w2c: the last row must be [0, 0, 0, 1]")
    R = w2c[:3, :3]
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > ROTATION_TOLERANCE or np.linalg.det(R) <= 0:
        raise fail(f"{name}.w2c: the 3x3 block is not a rotation (orthonormality error {err:.2g}, "
                   f"det {np.linalg.det(R):.3g})")
    if err > 1e-9:  # rounded by hand: use the nearest rotation, keeping the camera center
        eye = -R.T @ w2c[:3, 3]
        u, _, v = np.linalg.svd(R)
        w2c[:3, :3] = u @ v
        w2c[:3, 3] = -w2c[:3, :3] @ eye
    return PathKey(video_t=vt, w2c=w2c, fov_y_deg=fov, scene_t=st)
