"""Reading a NeRF-synthetic ("Blender") scene: transforms_{train,test}.json and RGBA images.

Each frame's ``transform_matrix`` is camera-to-world with OpenGL/Blender camera axes (x right,
y up, z backward); flipping its y and z columns gives OpenCV axes, and inverting it the viewmat.
The focal length comes from ``camera_angle_x`` (square pixels, principal point at the centre).
Images are composited over `background` with their alpha kept. The format has no point cloud, so
random points in a box stand in for one, as 3DGS does.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .cameras import Camera, SceneData, composite, read_image, resize_view, rigid_transform_problem
from .errors import DataError

# OpenGL camera axes (y up, z backward) to OpenCV (y down, z forward): negate y and z.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _load_json(path: Path) -> dict:
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise DataError(f"{path}: not valid JSON in UTF-8 ({error})") from None
    if not isinstance(meta, dict):
        raise DataError(
            f"{path}: expected a JSON object with 'camera_angle_x' and 'frames', found {_json_type(meta)}"
        )
    return meta


def _json_type(value) -> str:
    """What a parsed JSON value is, in JSON's words."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    names = {dict: "an object", list: "an array", str: "a string", int: "a number", float: "a number"}
    return names.get(type(value), type(value).__name__)


def _is_number(value) -> bool:
    """A JSON number (bool is an int subclass in Python, but true/false are not numbers)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _brief(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _camera_angle(path: Path, meta: dict) -> float:
    """camera_angle_x, the horizontal field of view in radians: tan(angle / 2) sets the focal length,
    so it must lie strictly between 0 and π."""
    angle = meta["camera_angle_x"]
    if not (_is_number(angle) and 0.0 < angle < math.pi):
        raise DataError(
            f"{path}: 'camera_angle_x' must be the horizontal field of view as a number of radians in (0, π), "
            f"got {_brief(angle)}"
        )
    return float(angle)


def _frame_pose(where: str, value) -> np.ndarray:
    """A frame's transform_matrix as a (4, 4) float64 rigid camera-to-world transform; DataError
    at `where` (file and frame) otherwise."""
    rows_ok = isinstance(value, list) and len(value) == 4 and all(
        isinstance(row, list) and len(row) == 4 and all(_is_number(v) for v in row) for row in value
    )
    if not rows_ok:
        raise DataError(f"{where}: 'transform_matrix' must be a 4x4 list of numbers (4 rows of 4), got {_brief(value)}")
    c2w = np.array(value, dtype=np.float64)
    problem = rigid_transform_problem(c2w, "transform_matrix")
    if problem is not None:
        raise DataError(f"{where}: {problem} (a rigid camera-to-world pose)")
    return c2w


def _frame_file(where: str, value) -> str:
    expected = "the image path relative to the scene folder, e.g. './train/r_0'"
    if not isinstance(value, str):
        raise DataError(f"{where}: 'file_path' is {_json_type(value)}; expected a string: {expected}")
    if not value.strip():
        raise DataError(f"{where}: 'file_path' is empty; expected {expected}")
    return value


def _frame_image_path(root: Path, file_path: str) -> Path:
    """A frame's image file: file_path relative to the scene folder, '.png' added when it has no
    suffix (the original NeRF-synthetic files leave it out)."""
    path = root / file_path
    return path if path.suffix else path.with_suffix(".png")


def _read_frames(path: Path, meta: dict, split: str) -> list[tuple[np.ndarray, str]]:
    """(camera-to-world, file_path) of every frame of a transforms file, each checked, so that a
    malformed file is reported before any image is read."""
    frames = meta["frames"]
    if not isinstance(frames, list):
        raise DataError(f"{path}: 'frames' is {_json_type(frames)}; expected a list of frame objects")
    if split == "train" and not frames:
        raise DataError(f"{path}: 'frames' is empty; expected at least one training frame")
    expected = {"file_path": "the image path relative to the scene folder",
                "transform_matrix": "a 4x4 list of numbers, camera-to-world"}
    checked = []
    for index, frame in enumerate(frames):
        where = f"{path}: frame {index}"
        if not isinstance(frame, dict):
            raise DataError(
                f"{where} is {_json_type(frame)}; expected an object with 'file_path' and 'transform_matrix'"
            )
        for key, what in expected.items():
            if key not in frame:
                raise DataError(
                    f"{where} needs 'file_path' and a numeric 'transform_matrix'; it has no {key!r} (expected {what})"
                )
        checked.append((_frame_pose(where, frame["transform_matrix"]), _frame_file(where, frame["file_path"])))
    return checked


def _read_split(root: Path, split: str, background, downscale: float) -> list[Camera]:
    """Cameras of transforms_<split>.json, with their images."""
    path = root / f"transforms_{split}.json"
    meta = _load_json(path)
    if "camera_angle_x" not in meta or "frames" not in meta:
        raise DataError(f"{path}: needs 'camera_angle_x' and 'frames'")
    angle = _camera_angle(path, meta)
    cameras = []
    for c2w, file_path in _read_frames(path, meta, split):
        image_path = _frame_image_path(root, file_path)
        rgb, alpha = read_image(image_path)
        size = (round(rgb.shape[1] / downscale), round(rgb.shape[0] / downscale))
        rgb, alpha = resize_view(rgb, alpha, size)
        width, height = size
        focal = 0.5 * width / math.tan(0.5 * angle)
        K = np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])
        viewmat = np.linalg.inv(c2w @ _GL_TO_CV)
        if alpha is not None:
            rgb = composite(rgb, alpha, background)
        # An image outside the scene folder ('../x.png', an absolute path) is named by its file_path.
        name = image_path.relative_to(root).as_posix() if image_path.is_relative_to(root) else file_path
        cameras.append(Camera(name, viewmat, K, width, height, rgb, alpha))
    return cameras


def load_blender(
    path, *, background=(1.0, 1.0, 1.0), downscale: float = 1, n_points: int = 100_000, bound: float = 1.3,
    seed: int = 0,
) -> SceneData:
    """Read a NeRF-synthetic scene folder.

    Training views from transforms_train.json; test views from transforms_test.json, else
    transforms_val.json, else none. background: (3,) colour the RGBA images are composited over.
    downscale: divide the image size by this. Points: n_points uniform in the cube [-bound, bound]^3
    with uniform random colours (3DGS's initialisation for this format), from `seed`.
    Raises DataError for a missing folder, JSON file or image, malformed JSON, or a transforms file
    whose field of view, frames, poses (rigid 4x4 camera-to-world) or file paths are not valid.
    """
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"{root}: Blender scene folder not found")
    if not (root / "transforms_train.json").is_file():
        raise DataError(f"{root}: transforms_train.json not found")
    train = _read_split(root, "train", background, downscale)
    test_split = next((s for s in ("test", "val") if (root / f"transforms_{s}.json").is_file()), None)
    test = _read_split(root, test_split, background, downscale) if test_split else []
    rng = np.random.default_rng(seed)
    points = rng.uniform(-bound, bound, (n_points, 3))
    return SceneData(root.name, train, test, points, rng.random((n_points, 3)), background=background)
